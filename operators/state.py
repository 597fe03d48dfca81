# SPDX-License-Identifier: GPL-3.0-or-later
"""What the add-on keeps between operator calls (in memory only, not saved in the .blend)."""

#: Extra cancel checks consulted for every progress report of a fit or preview (:mod:`.worker`):
#: ``hook(stage, fraction) -> bool`` (True cancels).  For scripts and tests;
#: the interactive path cancels with Esc.
PROGRESS_HOOKS = []

#: Last FitResult per mesh object name (the model behind the rig; for
#: scripting and tests — not saved in the .blend).
LAST_RESULTS = {}


def last_result(obj):
    return LAST_RESULTS.get(obj.name)


def _forget():
    """What the add-on keeps between fits: the worker (with its segmentations) and the last results."""
    from .worker import forget
    forget()
    LAST_RESULTS.clear()
