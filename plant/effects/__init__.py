"""Physical effects, each a small numba function on floats and flat arrays.

The axis kernel (:mod:`plant.kernel`) composes them; every function here can
be called and tested on its own.
"""
