"""Bleed points: where and how fast a scene bleeds (ml/s), whatever the bleeding method."""
import numpy as np

from sims.scene import keyframes


class BleedPoint:
    """A validated scene bleed point: position and rate (ml/s), linear along its keyframes, on in [start, stop)."""

    def __init__(self, item: dict):
        self.name, self.item = item["name"], item

    def position_at(self, t_s: float) -> np.ndarray:
        return np.asarray(keyframes.interpolate(self.item["path"], "position_mm", t_s, self.item["position_mm"]), np.float64)

    def rate_at(self, t_s: float) -> float:
        """ml/s before coagulation; 0 outside [start_s, stop_s)."""
        stop = self.item["stop_s"]
        if t_s < self.item["start_s"] or (stop is not None and t_s >= stop):
            return 0.0
        return float(keyframes.interpolate(self.item["path"], "rate_ml_s", t_s, self.item["rate_ml_s"]))
