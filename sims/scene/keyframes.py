"""Scripted keyframe paths: [{t_s, <name>: value or None, ...}] sorted by t_s (validated in sims.scene.config)."""
import numpy as np


def interpolate(path: list, name: str, t_s: float, default):
    """Value of `name` at t_s: linear between the keyframes that set it, held before the first and
    after the last; `default` when no keyframe sets it."""
    keys = [(frame["t_s"], frame[name]) for frame in path if frame.get(name) is not None]
    if not keys:
        return default
    times = [time for time, _ in keys]
    index = int(np.searchsorted(times, t_s, side="right"))
    if index == 0:
        return keys[0][1]
    if index == len(keys):
        return keys[-1][1]
    (t0, v0), (t1, v1) = keys[index - 1], keys[index]
    w = (t_s - t0) / (t1 - t0)
    return (1.0 - w) * np.asarray(v0, np.float64) + w * np.asarray(v1, np.float64)


def hold(path: list, name: str, t_s: float, default):
    """Value of `name` set by the last keyframe at or before t_s (a switch), else `default`."""
    value = default
    for frame in path:
        if frame["t_s"] <= t_s and frame.get(name) is not None:
            value = frame[name]
    return value
