"""The tables of recorded data, defined once (DESIGN.md section 6).

**Specimens table** (one row per specimen)::

    specimen   str    unique id
    region     str    brain region (e.g. ``cortex``)
    brain      str    id of the donor brain (integers are accepted and turned into text)
    radius_mm  float  undeformed radius R [mm], > 0
    height_mm  float  undeformed height H [mm], > 0
    ends       str    optional: ``glued`` (default), ``slip`` (lubricated) or ``unglued``
                      (rough plates without glue: held tangentially, the top plate lifts
                      off instead of pulling; :mod:`brain_fe.contact`)
    ...               any further columns (``notes``, composition, ...) are kept

**Recordings table** (one row per sample point)::

    specimen            str    specimen id (or a region name for region-averaged curves)
    test                str    ``compression_tension`` or ``torsion``
    amplitude           float  stretch amplitude A in (0, 1) (protocol 1 -> 1-A -> 1 -> 1+A -> 1)
                               or maximum amount of shear at the outer radius (> 0)
    cycle               int    >= 1
    branch              str    ``loading`` or ``unloading``
    time_s              float  time [s], finite, non-decreasing within a series
    stretch             float  lambda = h / H [-], compression_tension rows: required, > 0
    shear               float  gamma = theta R / H [-] at the outer radius, torsion: required
    nominal_stress_kPa  float  F / (pi R^2) [kPa], compression_tension rows: required
    torque_mNmm         float  torque on the top plate [mN mm], torsion rows: required
    axial_force_mN      float  axial force [mN], optional (empty / NaN allowed)
    ...                        any further columns (e.g. ``shear_stress_kPa``) are kept

A *series* (one curve) is all rows with the same ``(specimen, test, amplitude)``, in file
order, named by its test key (:func:`brain_fe.vocabulary.test_key`).
"""

from __future__ import annotations

from brain_fe.vocabulary import (
    AXIAL_FORCE,
    COMPRESSION_TENSION,
    LOADING,
    NOMINAL_STRESS,
    SHEAR,
    STRETCH,
    TIME,
    TORQUE,
    TORSION,
    UNLOADING,
)

SPECIMEN_COLUMNS = ("specimen", "region", "brain", "radius_mm", "height_mm")
SPECIMEN_ENDS = ("glued", "slip", "unglued")  # the optional ``ends`` column
RECORDING_COLUMNS = ("specimen", "test", "amplitude", "cycle", "branch", TIME, STRETCH,
                     SHEAR, NOMINAL_STRESS, TORQUE, AXIAL_FORCE)
RECORDED_BRANCHES = (LOADING, UNLOADING)
# Columns required for every row, and those required only by rows of one test.
ALWAYS = ("specimen", "test", "amplitude", "cycle", "branch", TIME)
BY_TEST = {COMPRESSION_TENSION: (STRETCH, NOMINAL_STRESS), TORSION: (SHEAR, TORQUE)}
FLOAT_COLUMNS = (TIME, STRETCH, SHEAR, NOMINAL_STRESS, TORQUE, AXIAL_FORCE)
# The controlled value may exceed the series amplitude by this fraction of the amplitude
# (round-off of a written file), not more.
AMPLITUDE_RTOL = 1e-6
# Physically meaningful data (recordings.tables._check_physics): a curve needs this many
# points, and its ramps (runs of one cycle and branch) this many each (median), to tell
# its shape from noise; specimens are mm-sized
MIN_SERIES_POINTS = 5
MIN_RAMP_POINTS = 3
RADIUS_RANGE_MM = (0.1, 100.0)
HEIGHT_RANGE_MM = (0.1, 200.0)
