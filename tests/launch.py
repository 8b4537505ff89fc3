"""The environment of a child process a test launches (``brainmech`` or ``mpirun``): free
of the MPI variables of the pytest process itself (which may run under ``mpirun``), allowed
to run as root and to oversubscribe the cores, one OpenMP thread."""

import os


def child_env() -> dict:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("OMPI_COMM_WORLD", "OMPI_MCA_ess", "PMIX_", "PMI_"))}
    env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMP_NUM_THREADS="1",
               PYTHONDONTWRITEBYTECODE="1")
    env.setdefault("OMPI_MCA_btl", "self,vader")
    return env
