"""Shared test helpers: synthetic meshes and parameter sets."""
import signal

from sims.scene import params


def tissue_values(**changes) -> dict:
    values = dict(params.TISSUE_PRESETS["liver"])
    values.update(changes)
    return values


def cautery_values(**changes) -> dict:
    values = {name: spec.default for name, spec in params.CAUTERY.items()}
    values["bottom"] = "body"
    values.update(changes)
    return values


def surface_only_values(**changes) -> dict:
    """Cautery values under which a field uniform in depth stays uniform: insulated bottom, no loss to air. The layered
    model then spreads heat exactly as a surface-only one."""
    from sims.heat.cautery import SURFACE_ONLY

    return cautery_values(**{**SURFACE_ONLY, **changes})


def interruptible() -> None:
    """Popen preexec_fn: SIGINT back to its default in the child, so the child's Python turns it into
    KeyboardInterrupt even when this test run was started with SIGINT ignored (a background job of a script)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
