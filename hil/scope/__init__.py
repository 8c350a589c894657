"""``hil scope``: a run's status and signals in a browser, live or after the run, read
from its run folder (:mod:`hil.scope.command`)."""
