"""One simulator interface (:class:`simulators.base.Simulator`) and its implementations:
the FE model on the recorded path (:mod:`simulators.fe`), the homogeneous analytical model
(:mod:`simulators.homogeneous`), the glued-cube composite (:mod:`simulators.glued_cube`)
and the MLP surrogates (:mod:`simulators.surrogate`).  Identification and diagnosis use
them alike."""
