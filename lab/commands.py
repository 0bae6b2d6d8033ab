"""What a front end asks a LabSession to do, as small named commands: queued by the session's methods on any thread
(after checking every value), applied in order by LabSession.tick on the simulation thread. A reader follows a
slider from its handler to `SetParameters` here, to sims.scene.parameters.SceneParameters.set_parameter, to the
model's set().

Where a burst of requests only needs its last (a slider dragged, a tool dragged, scenes switched), the session keeps
the latest values and queues one command that takes them (SetParameters, PlaceTools, SwitchScene): a drag of a
hundred events costs one command.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class Command:
    """One change to the running session; apply(session) runs on the simulation thread and may raise Refused (the
    scene may have changed since the command was checked: the session shows the reason)."""

    def apply(self, session) -> None:
        raise NotImplementedError


@dataclass(frozen=True)
class SetParameters(Command):
    """The latest value of each live parameter changed since the last SetParameters (LabSession.set_parameter)."""

    def apply(self, session) -> None:
        session._apply_parameters()


@dataclass(frozen=True)
class RebuildWith(Command):
    """A parameter that needs a rebuild: kept as an override, the scene rebuilt once the changes stop."""

    config_key: str
    value: float

    def apply(self, session) -> None:
        session._rebuild_with(self.config_key, self.value)


@dataclass(frozen=True)
class SetQuality(Command):
    """A quality preset (lab.session.QUALITY) by a rebuild."""

    name: str

    def apply(self, session) -> None:
        session._apply_quality(self.name)


@dataclass(frozen=True)
class SwitchScene(Command):
    """The scene the latest switch asked for (LabSession.switch_scene, back_to_scene_file), built once."""

    def apply(self, session) -> None:
        session._apply_switch()


@dataclass(frozen=True)
class Reset(Command):
    """Back to t = 0 with every value as it is now (Replay)."""

    def apply(self, session) -> None:
        session._reset()


@dataclass(frozen=True)
class SingleStep(Command):
    """One step while paused."""

    def apply(self, session) -> None:
        session.single_steps += 1


@dataclass(frozen=True)
class PlaceTools(Command):
    """The latest hand placement of each tool moved since the last PlaceTools (take_over, set_resting)."""

    def apply(self, session) -> None:
        session._apply_placements()


@dataclass(frozen=True)
class SetEnergized(Command):
    """A hand switches a tool on or off."""

    tool: str
    on: bool

    def apply(self, session) -> None:
        session.scene.set_energized(self.tool, self.on)


@dataclass(frozen=True)
class Release(Command):
    """One tool (every tool with None) back to its script."""

    tool: str | None

    def apply(self, session) -> None:
        session.scene.release(self.tool)


@dataclass(frozen=True, eq=False)
class AddBleedPoint(Command):
    """A bleed point with the default rate and radius at the surface texel nearest position_mm (3,) mm."""

    position_mm: np.ndarray

    def apply(self, session) -> None:
        session._add_point(self.position_mm)


@dataclass(frozen=True)
class RemoveBleedPoint(Command):
    """A bleed point (the last one with None) goes."""

    name: str | None

    def apply(self, session) -> None:
        session._remove_point(self.name)


@dataclass(frozen=True, eq=False)
class MoveBleedPoint(Command):
    """A bleed point to the surface texel nearest position_mm (3,) mm; a scene-file point's move is kept as an override."""

    name: str
    position_mm: np.ndarray

    def apply(self, session) -> None:
        session.overrides.update(session.scene.move_bleed_point(self.name, self.position_mm))
