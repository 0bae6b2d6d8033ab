"""What a hand or a script does to a running scene: place, switch and release tools, rest them on the tissue, find
the tissue along a ray, and add, move and remove bleed points. A mixin of sims.scene.assembly.Scene."""
import numpy as np

from sims.core.quoting import quote
from sims.scene import params
from sims.scene.checked import Refused, checked_flag, checked_number, finite_vector, unit_direction

POSITION_MARGIN_MM = 100.0  # a hand may place a tool this far outside the mesh's bounding box at most


class HandInteraction:
    """Scene's tools and bleed points by hand (it reads self.instruments, self.surface, self.time_s, self.config and
    the bleeding model's points; texel_near and checked_position find where a hand points)."""

    def instrument(self, name: str):
        """The tool of that name, or Refused."""
        for tool in self.instruments:
            if tool.name == name:
                return tool
        raise Refused(f"no instrument {quote(name)} in this scene")

    def add_instrument(self, tool) -> None:
        """A suction tool added at run time (heating tools are compiled into the heat model and need a rebuild)."""
        if tool.suction is None:
            raise Refused(f"{tool.name}: only suction tools can be added to a running scene")
        if any(other.name == tool.name for other in self.instruments):
            raise Refused(f"{tool.name}: there is a tool of that name already")
        self.instruments.append(tool)

    def checked_position(self, position_mm, name: str) -> np.ndarray:
        """position_mm as 3 finite numbers (mm) within POSITION_MARGIN_MM of the tissue's bounding box, or Refused."""
        position = finite_vector(position_mm, 3, name)
        lo, hi = self.surface.vertices_mm.min(axis=0), self.surface.vertices_mm.max(axis=0)
        if (position < lo - POSITION_MARGIN_MM).any() or (position > hi + POSITION_MARGIN_MM).any():
            raise Refused(f"{name}: {position.round(1).tolist()} mm is more than {POSITION_MARGIN_MM:g} mm outside the tissue's bounding box")
        return position

    def take_over(self, name: str, position_mm, direction=None, roll_deg: float | None = None) -> None:
        """A hand places the tool (mm; direction handle -> tip, any length; roll in degrees): it leaves its script's path
        until release(). Omitted direction and roll keep the tool's current ones."""
        from sims.scene.instruments import HandPlacement

        tool = self.instrument(name)
        pose = tool.pose_at(self.time_s)
        position = self.checked_position(position_mm, f"{name}: position_mm")
        direction = unit_direction(pose.direction if direction is None else direction, f"{name}: direction")
        roll = pose.roll_deg if roll_deg is None else float(finite_vector([roll_deg], 1, f"{name}: roll_deg")[0])
        tool.hand = HandPlacement(position, direction, roll)

    def set_energized(self, name: str, on: bool) -> None:
        """A hand switches the tool on or off (until release())."""
        on = checked_flag(on, f"{name}: energized")
        self.instrument(name).energized_by_hand = bool(on)

    def release(self, name: str | None = None) -> None:
        """Give one tool (every tool with None) back to its script."""
        for tool in self.instruments if name is None else [self.instrument(name)]:
            tool.release()

    def held_tools(self) -> list[str]:
        """Names of the tools a hand holds (placed or switched), in scene order."""
        return [tool.name for tool in self.instruments if tool.held]

    def tissue_distance_mm(self, position_mm, direction) -> float | None:
        """How far the tissue is from a point along a direction (mm), or None when the ray misses it."""
        from sims.surface.raycast import first_hit

        direction = np.asarray(direction, np.float64) / np.linalg.norm(direction)
        origin = np.asarray(position_mm, np.float64)
        return first_hit(origin, direction, self._triangles_along(origin[None], direction))

    def _triangles_along(self, starts: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """The tissue's triangles (K, 3, 3) mm that rays from starts (N, 3) mm along the unit direction (3,) may cross:
        those whose bounding box meets the box holding the rays through the tissue. Few for rays close together along
        an axis (a flat tool's, straight down): each ray then costs a fraction of one through the whole mesh."""
        if self._triangles_mm is None:
            triangles = self.surface.vertices_mm[self.surface.faces]
            self._triangles_mm = triangles, np.ascontiguousarray(triangles.min(axis=1).T), np.ascontiguousarray(triangles.max(axis=1).T)
        triangles, low, high = self._triangles_mm
        tissue_low, tissue_high = low.min(axis=1), high.max(axis=1)
        through = np.linalg.norm(starts - (tissue_low + tissue_high) / 2, axis=1).max() + np.linalg.norm(tissue_high - tissue_low) / 2
        ends = starts + direction * through  # past the tissue's far side
        slack = 1e-3  # mm: a ray along a triangle's edge keeps it
        box_low, box_high = np.minimum(starts, ends).min(axis=0) - slack, np.maximum(starts, ends).max(axis=0) + slack
        keep = np.ones(len(triangles), bool)
        for axis in range(3):  # one axis at a time: rows of (3, F) compare faster than a (F, 3) array
            keep &= (low[axis] <= box_high[axis]) & (high[axis] >= box_low[axis])
        return triangles[keep]

    def _tissue_gap_mm(self, name: str, pose, behind_mm: float) -> float | None:
        """Smallest gap (mm, negative: pressed in) between the tool at this pose and the tissue, along the direction
        it is lowered (sims.scene.instruments.Instrument.contact_points_mm, lowered_along); each ray starts behind_mm back, so
        a tool pressed in still finds the surface. None when every ray misses the tissue."""
        from sims.surface.raycast import first_hit

        tool = self.instrument(name)
        direction = tool.lowered_along(pose)
        starts = tool.contact_points_mm(pose) - direction * behind_mm
        triangles = self._triangles_along(starts, direction)
        hits = [hit for hit in (first_hit(start, direction, triangles) for start in starts) if hit is not None]
        return min(hits) - behind_mm if hits else None

    def tool_clearance_mm(self, name: str) -> float | None:
        """Gap between the tool and the tissue, mm (negative: pressed in), or None when there is no tissue to meet:
        measured along the tool's axis from its tip, or for a flat tool straight down from its blade (the way
        rest_on_tissue lowers it)."""
        pose = self.instrument(name).pose_at(self.time_s)
        key = (name, tuple(pose.position_mm), tuple(pose.direction), pose.roll_deg)
        if key not in self._clearances:  # the stats ask twice a second; a tool at rest needs no new ray
            if len(self._clearances) > 64:
                self._clearances.clear()
            self._clearances[key] = self._tissue_gap_mm(name, pose, behind_mm=5.0)
        return self._clearances[key]

    def rest_on_tissue(self, name: str, position_mm, depth_mm: float, direction=None, roll_deg=None) -> float | None:
        """Place the tool by hand so that it is depth_mm into the tissue below position_mm, as a hand rests it: lowered
        along its axis until its tip is in, or a flat tool straight down until its blade's lowest point is in. Returns
        the distance moved (mm), or None when there is no tissue under it (then it is placed at position_mm)."""
        self.take_over(name, position_mm, direction, roll_deg)
        tool = self.instrument(name)
        pose = tool.pose_at(self.time_s)
        reach = float(np.ptp(self.surface.vertices_mm, axis=0).max()) + POSITION_MARGIN_MM  # starts behind any tissue
        gap = self._tissue_gap_mm(name, pose, reach)
        if gap is None:
            return None
        moved = gap + float(depth_mm)
        tool.hand.position_mm = tool.hand.position_mm + tool.lowered_along(pose) * moved
        return moved

    def bleed_point(self, name: str):
        """The bleed point of that name, or Refused."""
        for point in self.bleed_points:
            if point.name == name:
                return point
        raise Refused(f"no bleed point {quote(name)} in this scene")

    def _file_index(self, point) -> int | None:
        """The point's index in the scene file's bleed_points, or None for a point added at run time."""
        return next((index for index, item in enumerate(self.config["bleed_points"]) if item is point.item), None)

    def remove_bleed_point(self, name: str) -> None:
        point = self.bleed_point(name)
        self.bleed_points.remove(point)

    def move_bleed_point(self, name: str, position_mm) -> dict:
        """Move a bleed point to the surface texel nearest position_mm (it leaves its path). Returns {config key: value}
        of what changed in the scene config."""
        point = self.bleed_point(name)
        texel = self.texel_near(self.checked_position(position_mm, f"{name}: position_mm"))
        point.item["position_mm"] = [float(v) for v in self.surface.position_mm[texel]]
        point.item["path"] = []
        index = self._file_index(point)
        if index is None:
            return {}
        return {f"bleed_points.{index}.position_mm": list(point.item["position_mm"]), f"bleed_points.{index}.path": []}

    def surface_hit(self, ray_origin, ray_direction) -> np.ndarray | None:
        """The surface texel position (mm) where a ray (a click) first meets the tissue, or None."""
        origin = finite_vector(ray_origin, 3, "ray_origin")
        if np.abs(origin).max() > 1.0e6:
            raise Refused(f"ray_origin: {origin.tolist()} is more than a kilometre away")
        direction = unit_direction(ray_direction, "ray_direction")
        distance = self.tissue_distance_mm(origin, direction)
        if distance is None:
            return None
        hit = origin + distance * direction
        return self.surface.position_mm[self.texel_near(hit)].astype(np.float64)

    def add_bleed_point(self, name: str, position_mm, rate_ml_s: float, radius_mm: float = 0.5):
        """A new bleed point from now on (bleeding model only); returns it."""
        from sims.scene.bleed_points import BleedPoint

        if "bleeding" not in self._models:
            raise Refused("this scene has no bleeding model")
        if any(point.name == name for point in self.bleed_points):
            raise Refused(f"there is a bleed point {quote(name)} already")
        position = self.checked_position(position_mm, f"{name}: position_mm")
        rate = checked_number(params.BLEED_POINT["rate_ml_s"], rate_ml_s)
        radius = checked_number(params.BLEED_POINT["radius_mm"], radius_mm)
        point = BleedPoint({"name": name, "position_mm": [float(v) for v in position], "rate_ml_s": rate,
                            "radius_mm": radius, "start_s": 0.0, "stop_s": None, "path": []})
        self.bleed_points.append(point)
        return point
