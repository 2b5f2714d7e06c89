"""Stage 2: register prepared frames of a session in seq order, under a lease, and publish the results.

stage       RegisterStage: the held sessions, kicks, take-over, and `step`, one session served in named steps
lease       the lease and the fence (LeaseKeeper, LeaseLostError)
cursor      the cursor and replay: frames to registration in seq order, added, lost or rejected (Cursor)
flush       flush timing: what is published, and when (Flusher)
completion  a finished session's final flush, or its empty result (Completion)
poison      registration failures counted, a frame that keeps failing dead-lettered (PoisonCounter)
held        HeldSession, the plain data they share (the bottom module)
"""

from workers.stages.register.stage import RegisterStage

__all__ = ["RegisterStage"]
