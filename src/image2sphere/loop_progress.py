"""How far a Lightning checkpoint's training got, read from its loop state: the epochs done and the batches done
in the epoch in progress.

Kept apart from :mod:`image2sphere.training.checkpoint` (which imports Lightning) so that readers of run
directories (:mod:`image2sphere.reporting.runs`, behind ``src.tables``) use the same reading without
importing Lightning.
"""

from __future__ import annotations

__all__ = ["batches_done_in_epoch", "epoch_resumed_in", "has_loop_state"]


def has_loop_state(checkpoint: dict) -> bool:
    """Whether ``checkpoint`` has Lightning's count of epochs processed (written by every Lightning 2 fit)."""
    try:
        return "processed" in checkpoint["loops"]["fit_loop"]["epoch_progress"]["current"]
    except (KeyError, TypeError):
        return False


def batches_done_in_epoch(checkpoint: dict) -> int:
    """Training batches of the checkpoint's current epoch that were done (0 for a checkpoint at an epoch's end)."""
    try:
        progress = checkpoint["loops"]["fit_loop"]["epoch_loop.batch_progress"]
        # a checkpoint written at a batch's end has processed that batch but not yet marked it completed
        done = int(progress["current"]["processed"])
    except (KeyError, TypeError, ValueError):
        return 0
    return 0 if progress.get("is_last_batch", True) else done


def epoch_resumed_in(checkpoint: dict) -> int:
    """The training epoch a run resumed from ``checkpoint`` starts in: the one Lightning tells the samplers
    (its count of epochs processed; a checkpoint written at an epoch's end starts the next one)."""
    try:
        return int(checkpoint["loops"]["fit_loop"]["epoch_progress"]["current"]["processed"])
    except (KeyError, TypeError, ValueError):
        return int(checkpoint.get("epoch", 0) or 0)
