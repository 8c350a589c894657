"""Traces for ``hil bench identify``: an axis simulated from a machine file's documented
equations with ``scipy.integrate.solve_ivp`` (never the plant's kernel), a Sinumerik-style
controller cascade written for it, noise and quantisation, the conventions in the header."""
