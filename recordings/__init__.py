"""Recorded data, defined once: the specimens and recordings tables (:mod:`.schema`,
:mod:`.tables`, :mod:`.cells`), the observation table the simulators predict
(:mod:`.observations`), synthetic recordings from the FE model (:mod:`.synthetic`), the
virtual brain bank (:mod:`.brain_bank`) and the Budday et al. (2017) curves (:mod:`.budday`).
Below identification and diagnosis, which both read through it."""
