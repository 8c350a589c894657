"""``hil replay RUN``: the recorded run re-run offline on the setpoints it applied, compared
with its recording (:mod:`hil.replay.replay`), and what the demo derives from it: the
timing cost of the real run against the lock-step simulation (:mod:`hil.replay.timing`)."""

from hil.replay.machine_files import ReplayError
from hil.replay.replay import TOLERANCE, ChannelDifference, ReplayResult, replay_run

__all__ = ["TOLERANCE", "ChannelDifference", "ReplayError", "ReplayResult", "replay_run"]
