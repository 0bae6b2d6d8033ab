"""Checks of a built scene before it runs: what its user should be told, and what stops it (ConfigError). Front ends
print or show the notes; nothing here prints."""
from sims.heat.cautery import SubstepLimit
from sims.scene.config import ConfigError


def notes(scene) -> list[tuple[str, str]]:
    """(level, text) for the user: ("warning", "mesh: ...") when the mesh looks like one in metres, ("note", ...) for
    each retired key the scene file still holds (it is ignored)."""
    found = [("warning", f"mesh: {scene.surface.size_warning}")] if scene.surface.size_warning else []
    return found + [("note", note) for note in scene.config.get("notes", ())]


def check_runnable(scene) -> None:
    """Raise ConfigError when the explicit heat scheme would need more than sims.heat.cautery.MAX_SUBSTEPS substeps
    per step (a slider or an override can ask for that)."""
    if scene.cautery is not None:
        try:
            scene.cautery.substeps(scene.time_step_s)
        except SubstepLimit as exc:
            raise ConfigError(scene.file, "cautery.scheme", str(exc)) from None
