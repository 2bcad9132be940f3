"""Marking order inside layers: the groups of a job in input order, each ordered on its own.

Laser software marks layers with different settings, often one after the
other; :func:`split_groups` gives each group's sub-job and :func:`join_group_tours`
joins their closed tours into one, each opened where the jump from the previous
group's last stroke costs least.
"""
from __future__ import annotations

import numpy as np

from .path_job import Job, Timing, Tour, jump_cost, tour_points

__all__ = ["split_groups", "join_group_tours"]


def split_groups(job: Job, groups) -> list:
    """``(name, stroke indices, sub-job)`` per group, groups in the order they first appear."""
    names = list(dict.fromkeys(groups))
    out = []
    g = np.asarray(groups, dtype=object)
    for name in names:
        idx = np.flatnonzero(g == name)
        out.append((name, idx, Job(tuple(job.strokes[i] for i in idx))))
    return out


def join_group_tours(parts, timing: Timing, rotate: bool = True) -> Tour:
    """One tour of the whole job from each group's closed tour.

    Parameters
    ----------
    parts : list of (stroke indices (m,), sub-job, sub-tour)
        In the order the groups are marked.
    timing : Timing
        Jump cost used to choose where each group's tour is opened.
    rotate : bool
        False keeps every group's tour as it starts (the input order).
    """
    order, rev, entry = [], [], []
    prev_exit = None
    for idx, sub, t in parts:
        k = 0
        if rotate and prev_exit is not None and sub.n > 1:
            ein, eout = tour_points(sub, t)
            gain = jump_cost(np.hypot(*(ein - prev_exit).T), timing) - \
                jump_cost(np.hypot(*(ein - np.roll(eout, 1, axis=0)).T), timing)
            k = int(np.argmin(gain))
        o = np.roll(t.order, -k)
        order.append(idx[o])
        rev.append(np.roll(t.reverse, -k))
        entry.append(np.roll(t.entry, -k))
        _, eout = tour_points(sub, Tour(o, rev[-1], entry[-1]))
        prev_exit = eout[-1]
    return Tour(np.concatenate(order), np.concatenate(rev), np.concatenate(entry))
