"""Forward model: a specimen between two plates under a displacement-controlled protocol.

:class:`ForwardModel` composes the pieces of this package and compiles its forms once:

* a geometry with its kinematics (:mod:`brain_fe.geometry`: axisymmetric with twist, 3D),
* a material (:mod:`brain_fe.materials`: isochoric laws, a volumetric law, history
  wrappers),
* end conditions and the top-plate reactions (:mod:`brain_fe.ends`),
* the protocol stepper with cut-back (:mod:`brain_fe.stepper`) and Newton's method
  (:mod:`brain_fe.solver`),
* sensitivities (:mod:`brain_fe.sensitivities`) and the measurement layer
  (:mod:`brain_fe.artefacts`).

Every parameter is a ``fem.Constant`` keyed by its :class:`~brain_fe.parameters.Param`,
so running another parameter set or protocol costs no compilation.  Units: mm, kPa, mN,
mN mm, s.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence

import dolfinx.fem as fem
import dolfinx.fem.petsc as fem_petsc
import dolfinx.mesh as dmesh
import numpy as np
import pandas as pd
import ufl

from . import _compat
from . import artefacts as _art
from .artefacts import Artefacts
from .contact import LiftOff
from .ends import EndConditions, Interface, check_ends, resolve
from .geometry import Geometry
from .history import HistoryState, history_residual
from .materials import MaterialModel, MaterialParameters
from .parameters import K_R, K_THETA, Direction, Param, Parameters
from .protocols import Protocol, Step, plate_position
from .response import Response
from .sensitivities import Converged, DirectSensitivities, PathSensitivities
from .solver import NewtonSolver, ghost_forward, ghost_reverse
from .stepper import follow
from .vocabulary import TIME, channel_values

log = logging.getLogger(__name__)


def on_cells(form: ufl.Form, msh, cells: np.ndarray) -> ufl.Form:
    """``form`` with its cell integrals restricted to ``cells`` (owned cells of the mesh
    ``msh``, sorted); facet integrals are kept whole.  Its cell integrals must cover the
    whole mesh (restricting ``dx(k)`` of several regions would merge them)."""
    if any(i.integral_type() == "cell" and i.subdomain_id() != "everywhere"
           for i in form.integrals()):
        raise ValueError("on_cells: the form already has cell integrals over subdomains")
    tags = dmesh.meshtags(msh, msh.topology.dim, cells, np.ones(len(cells), dtype=np.int32))
    return ufl.Form([i.reconstruct(subdomain_id=1, subdomain_data=tags)
                     if i.integral_type() == "cell" else i for i in form.integrals()])


class ForwardModel:
    """Compiled forward model of one geometry, material and end condition.

    ``material`` (a :class:`~brain_fe.materials.MaterialModel`) or the shorthand of the
    built-in composition: ``n_terms`` Ogden terms, ``volumetric`` law, ``maxwell`` branches,
    ``mullins`` softening.  ``ends``: ``glued``, ``slip``, ``springs`` or ``unglued`` (glued
    with ``lift_off``); ``lift_off``: the top plate cannot pull, it lifts off instead
    (:mod:`brain_fe.contact`); ``degree``: of the displacement (and twist) field.
    """

    def __init__(self, geometry: Geometry, material: MaterialModel | None = None,
                 ends: str = "glued", degree: int = 2, *, n_terms: int = 1,
                 volumetric: str = "quadratic", maxwell: int = 0, mullins: bool = False,
                 lift_off: bool = False):
        check_ends(ends, geometry.kind)
        ends, lift_off = resolve(ends, lift_off)
        self.material = material or MaterialModel.build(n_terms, volumetric, maxwell,
                                                         mullins)
        self.geometry, self.ends_kind = geometry, ends
        msh = geometry.mesh
        self.comm = msh.comm
        self.V = _compat.vector_space(msh, degree, 3)
        self.u = fem.Function(self.V, name="displacement")
        st = _compat.scalar_type()
        _compat.stable_constant_counts()  # the forms' signatures, whatever came before
        _compat.fresh_label_counts()  # and those of the history update
        self.constants = {p: fem.Constant(msh, st(1.0))
                          for p in self.material.parameters() + EndConditions.parameters(ends)}
        self.c_dt = fem.Constant(msh, st(1.0))  # time increment of the (sub)step [s]
        self.ends = EndConditions(ends, geometry, self.V, self.u, fem.Constant(msh, st(0.0)),
                                  fem.Constant(msh, st(0.0)), self.constants)
        self.bcs = self.ends.bcs
        # UFL variables around the elastic constants: d(energy)/d(parameter)
        wrapped = {p for w in self.material.wrappers for p in w.parameters()} | {K_R, K_THETA}
        self.param_vars = {p: ufl.variable(c) for p, c in self.constants.items()
                           if p not in wrapped}
        t0 = time.perf_counter()
        self.residual_ufl = self._residual({**self.constants, **self.param_vars})
        self.residual_form = _compat.form(self.residual_ufl)
        self.jacobian_form = _compat.form(ufl.derivative(self.residual_ufl, self.u,
                                                         ufl.TrialFunction(self.V)))
        self._top_cells = self.ends.top_cells()
        self.reaction_form = self.at_top(self.residual_ufl)
        self._reaction_b = fem_petsc.create_vector(self.reaction_form)
        self.compile_time_s = time.perf_counter() - t0
        log.debug("compiled %s forms in %.1f s", geometry.kind, self.compile_time_s)
        self.newton = NewtonSolver(self.comm, self.residual_form, self.jacobian_form, self.u,
                                   self.bcs)
        self.lift_off = LiftOff(self.newton, self.ends, self.reactions,
                                self._axial_stiffness) if lift_off else None
        # history-dependent models, glue springs and lift-off follow their sensitivities
        # along the path
        self.path_sensitivities = (self.state is not None or ends == "springs"
                                   or self.lift_off is not None)
        self._sens = (PathSensitivities if self.path_sensitivities
                      else DirectSensitivities)(self)
        self.iterations = self.cutbacks = 0
        self.newton_log: list[tuple[float, list[float]]] = []

    def at_top(self, form: ufl.Form):
        """``form`` (a residual-like vector form) compiled on the cells with a dof on the
        top face alone, for its rows of the top plate (the reactions): a quarter to a fifth
        of the cost of the whole form on the working mesh, and the same bits in those rows
        (each sums the same cells' contributions in the same order)."""
        return _compat.form(on_cells(form, self.geometry.mesh, self._top_cells))

    def _residual(self, p):
        """The weak form: energy (elastic) or stress (history) part plus the glue layer."""
        v = ufl.TestFunction(self.V)
        g = self.geometry
        self.state = None
        if self.material.history:
            self.state = HistoryState(g, self.material.state_size)
            R = history_residual(self.material, g, self.u, v, self.state, p, self.c_dt)
        else:
            F = g.deformation_gradient(self.u)
            self.energy_density = self.material.strain_energy(F.T * F, ufl.det(F), p)
            R = ufl.derivative(self.energy_density * g.volume_weight() * g.dx, self.u, v)
        glue = self.ends.glue_energy()
        return R if glue is None else R + ufl.derivative(glue, self.u, v)

    # ------------------------------------------------------------------ parameters
    def parameter_values(self, params: MaterialParameters | Mapping,
                         interface: Interface | None = None) -> Parameters:
        """The typed values of every constant of this model; ValueError when ``params``
        need physics this model was not compiled with, or lack a value."""
        mat = self.material
        if isinstance(params, MaterialParameters):
            if len(params.mu) != mat.n_terms:
                raise ValueError(f"model compiled for {mat.n_terms} Ogden term(s), "
                                 f"got {len(params.mu)}")
            if params.maxwell != mat.maxwell:
                raise ValueError(f"model compiled for {mat.maxwell} Maxwell branch(es), "
                                 f"got {params.maxwell}")
            if params.softening and not mat.softening:
                raise ValueError("softening needs a model compiled with mullins=True")
            values = params.values()
        else:
            values = Parameters(params)
        if interface is not None:
            if self.ends_kind != "springs":
                raise ValueError("interface stiffnesses k_r, k_theta go with ends='springs'")
            values = values | interface.values()
        missing = [str(p) for p in self.constants if p not in values]
        if missing:
            what = ("the glue-layer stiffnesses (an Interface)" if "k_r" in missing
                    else ", ".join(missing))
            raise ValueError(f"this model needs {what}")
        return values

    def set_parameters(self, values: Parameters) -> None:
        for p, c in self.constants.items():
            c.value = values[p]
        mu_total = sum(values.family("mu"))
        self.newton.atol = 1e-10 * mu_total * math.pi * self.geometry.radius_mm ** 2  # mN

    # ------------------------------------------------------------------ outputs
    def reactions(self) -> tuple[float, float]:
        """(axial force [mN], torque [mN mm]) on the top plate at the current state."""
        b = self._reaction_b
        with b.localForm() as bl:
            bl.set(0.0)
        fem_petsc.assemble_vector(b, self.reaction_form)
        ghost_reverse(b)
        return self.ends.reactions(b, self.comm)

    def _at_converged(self, record: bool, path: bool) -> Converged:
        """The converged state's residual (where the reactions or path sensitivities need
        it), reactions (if ``record``) and history update, each computed once: the path
        sensitivities perturb and restore this state and reuse them."""
        base = Converged()
        if record or path:
            base.residual = (self.newton.free_residual() if self.lift_off is None
                             else self.newton.assemble_residual(with_bcs=False).copy())
        if record:
            base.reactions = self.ends.reactions(base.residual, self.comm)
        if self.state is not None:
            base.update = self.state.evaluate()
        return base

    def _axial_stiffness(self) -> float:
        """Small-strain axial stiffness of the specimen with slip ends, 3 mu A / H
        [mN/mm]: the first guess of the force-free search off the plate."""
        g = self.geometry
        mu_total = sum(float(c.value) for p, c in self.constants.items()
                       if p.family == "mu")
        return 3 * mu_total * math.pi * g.radius_mm ** 2 / g.height_mm

    def _set_control(self, test: str, value: float, preload: float = 0.0) -> None:
        """Plate position for ``value`` of the controlled quantity (and the preload)."""
        g = self.geometry
        self.ends.set_top(*plate_position(test, value, preload, g.height_mm, g.radius_mm))

    def _sensitivity_params(self, sensitivities) -> tuple[list, list[str]]:
        """([(key, Direction)] of the model constants, artefact names) to differentiate
        for ``sensitivities`` (Params, their names, Directions, artefact names)."""
        if not sensitivities:
            return [], []
        if sensitivities is True:
            return [(p, Direction.of(p)) for p in self.constants], []
        requests, arts = [], []
        for n in sensitivities:
            if isinstance(n, Direction):
                unknown = [str(p) for p, _ in n.weights if p not in self.constants]
                if unknown:
                    raise ValueError(f"direction {n}: this model has no {', '.join(unknown)}")
                requests.append((n, n))
            elif str(n) in _art.NAMES:
                arts.append(str(n))
            elif Param.parse(n) in self.constants:
                requests.append((Param.parse(n), Direction.of(Param.parse(n))))
            else:
                raise ValueError(f"no sensitivity for {n}; this model has "
                                 f"{', '.join(map(str, [*self.constants, *_art.NAMES]))}")
        return requests, arts

    # ------------------------------------------------------------------ protocol
    def run(self, protocol: Protocol, params, **kw) -> pd.DataFrame:
        """The table view of :meth:`solve`: ``time_s, cycle, branch, stretch|shear``, then
        ``nominal_stress_kPa, axial_force_mN`` (compression/tension) or ``torque_mNmm,
        shear_stress_kPa, axial_force_mN`` (torsion), then ``d_<column>/d_<param>``."""
        return self.solve(protocol, params, **kw).frame()

    def solve(self, protocol: Protocol, params, *, interface: Interface | None = None,
              artefacts: Artefacts | None = None, sensitivities: bool | Sequence = False,
              max_cutbacks: int = 6, field_output: str | None = None,
              callback: Callable[[int, int], None] | None = None) -> Response:
        """Follow ``protocol`` from the undeformed state; one output per protocol step.

        ``params``: :class:`MaterialParameters` or a mapping Param -> value of every
        constant; ``interface``: the glue stiffnesses (``ends="springs"``).
        ``sensitivities`` (True for every constant, or a list of Params / names, which may
        include the artefact names) adds partial derivatives of every output (kappa held
        fixed in d/d mu_p); geometric artefacts by central differences of whole runs.
        Raises :class:`~brain_fe.solver.ConvergenceError` when Newton fails after
        ``max_cutbacks`` halvings.
        """
        art = artefacts or Artefacts()
        values = self.parameter_values(params, interface)
        names, art_names = self._sensitivity_params(sensitivities)
        check_ends(self.ends_kind, self.geometry.kind, protocol.test)
        describe = params.describe if isinstance(params, MaterialParameters) else \
            (lambda: repr(values))
        with _art.scaled_mesh(self.geometry, art):
            res = self._follow(protocol, values, art, names, max_cutbacks, field_output,
                               callback, describe)
        R = self.geometry.radius_mm
        res.add_offsets(_art.offset_channels(protocol.test, R, art))
        for name in art_names:
            if name in _art.GEOMETRIC:
                h, runs = 1e-5, []
                for sign in (1, -1):
                    a = art.replace(name, art.values()[name] + sign * h)
                    with _art.scaled_mesh(self.geometry, a):
                        runs.append(self._follow(protocol, values, a, [], max_cutbacks, None,
                                                 None, describe))
                d = {c: (runs[0].values[c] - runs[1].values[c]) / (2 * h) for c in res.values}
            else:
                unit = Artefacts(force_offset_mN=1.0) if name == "force_offset" else \
                    Artefacts(torque_offset_mNmm=1.0)
                d = {c: np.full(len(res), v)
                     for c, v in _art.offset_channels(protocol.test, R, unit).items()}
            res.jacobian[Param.parse(name)] = d
        return res

    def _follow(self, protocol, values, art, names, max_cutbacks, field_output, callback,
                describe) -> Response:
        self.set_parameters(values)
        x = _compat.petsc_vec(self.u)
        x.set(0.0)
        ghost_forward(x)
        if self.state is not None:
            self.state.reset()
        if self.lift_off is not None:
            self.lift_off.reset()
        self.newton.forget()  # a run never depends on the runs before it
        if names:
            self._sens.start(names)
        steps = protocol.steps()
        R = self.geometry.radius_mm
        writer = _FieldWriter(self, field_output) if field_output else None
        rows, sens_rows = [], []

        def converged(step: Step | None):
            """Book-keeping after a converged (sub)step: sensitivities, outputs, history."""
            base = self._at_converged(record=step is not None,
                                      path=bool(names) and self.path_sensitivities)
            sens = self._sens.at_state(step is not None, base) if names else {}
            if step is not None:
                fz, torque = base.reactions
                rows.append({TIME: step.time_s, "cycle": step.cycle, "branch": step.branch,
                             "control": step.value,
                             **channel_values(protocol.test, fz, torque, R)})
                if self.lift_off is not None:
                    rows[-1]["in_contact"] = not self.lift_off.trial_off
                # the channels are linear in (force, torque)
                sens_rows.append({p: channel_values(protocol.test, dfz, dtq, R)
                                  for p, (dfz, dtq) in sens.items()})
                if writer:
                    writer.write(step.time_s)
            if self.lift_off is not None:
                self.lift_off.commit(*((step.time_s, step.value, step.cycle) if step else ()))
            if self.state is not None:
                self.state.scatter(base.update)

        try:
            log_ = follow(protocol, steps, x=x, newton=self.lift_off or self.newton,
                          set_control=lambda q, p: self._set_control(protocol.test, q, p),
                          set_dt=lambda dt: setattr(self.c_dt, "value", dt),
                          on_converged=converged, describe=describe,
                          preload=art.stretch_offset, max_cutbacks=max_cutbacks,
                          callback=callback)
        finally:
            if writer:
                writer.close()
        self.iterations, self.cutbacks, self.newton_log = (log_.iterations, log_.cutbacks,
                                                           log_.newton)
        res = Response.from_rows(protocol.test, rows, sens_rows)
        if self.lift_off is not None:
            res.contact_events = list(self.lift_off.events)
        return res


class _FieldWriter:
    """Displacement (and twist) field per output step, XDMF on a P1 interpolation."""

    def __init__(self, model: ForwardModel, path: str):
        self.file = _compat.xdmf_file(model.comm, path)
        self.file.write_mesh(model.geometry.mesh)
        self.model = model
        self.out = fem.Function(_compat.vector_space(model.geometry.mesh, 1, 3),
                                name="u_r,u_z,phi" if model.geometry.kind == "axisymmetric"
                                else "displacement")

    def write(self, t: float):
        self.out.interpolate(self.model.u)
        self.file.write_function(self.out, t)

    def close(self):
        self.file.close()
