"""The optional parts of the install: which extra of ``pyproject.toml`` brings a module.

The core (``hil run``, ``hil controller``, ``hil demo``, ``hil sim`` and every other
command not named here) needs only the project's dependencies.  Studies need Dask, SALib,
Optuna, uvloop (the workers' event loop) and Bokeh (Dask's dashboard graphs); the MDF4
export needs asammdf; ``hil scope`` needs Bokeh (its own extra, ``scope``, so that a
commissioning machine need not install Dask for it; ``study`` lists it too).  ``pip
install -e '.[all]'`` brings them all, and the README's test command does too (the
``test`` extra includes ``all``).

A command that imports a missing one ends with :func:`missing_extra`'s message, from
:func:`hil.cli.main`, the one place that catches it."""

#: top-level module -> the extra that installs it (tests/test_extras.py holds this
#: against pyproject.toml's optional dependencies)
EXTRA_OF_MODULE = {
    "dask": "study",
    "distributed": "study",
    "SALib": "study",
    "optuna": "study",
    "uvloop": "study",
    "bokeh": "scope",
    "asammdf": "mdf",
}


def missing_extra(exc: ModuleNotFoundError, command: str) -> str | None:
    """The message for ``command`` (e.g. ``"hil study"``) that failed on ``exc``, naming
    the extra to install; None when the missing module is no extra's (a broken install,
    reported as it is)."""
    module = (exc.name or "").split(".")[0]
    extra = EXTRA_OF_MODULE.get(module)
    if extra is None:
        return None
    return (f"{command} needs the optional '{extra}' packages ({module} is not installed): "
            f"pip install 'feeddrive-hil[{extra}]' (in a checkout: "
            f"python3 -m pip install -e '.[{extra}]'; '.[all]' brings every extra)")
