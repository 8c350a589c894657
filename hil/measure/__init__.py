"""The controller's measurement functions, independent of any plant: PRBS excitation
(:mod:`hil.measure.prbs`), frequency-response estimation with averaging
(:mod:`hil.measure.frequency_response`) and the triggered servo-trace recorder
(:mod:`hil.measure.trace`)."""
