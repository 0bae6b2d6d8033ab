"""A drill driven through lab.session.LabSession, as the browser drives it but from a script: scenes/hemostasis.yaml,
the tip temperature set to 110 C, the ball electrode taken by hand, rested on the bleeding vessel and switched on, then
lifted; prints the vessel's bleed rate (ml/s), the blood (ml) and the burn (mm, mm^2) along the way.

Run: python examples/drill_session.py [--arch cpu|gpu|auto]   (about 5 s on 2 CPU cores once the kernels are cached)
"""
import argparse

from lab.session import LabSession
from sims.core.backend import ARCH_CHOICES
from sims.scene.checked import Refused
from sims.scene.config import REPO_ROOT

BALL = "ball_electrode"
TIP = f"instruments.{BALL}.tip_temperature_c"  # a key of session.parameters()


def play_until(session: LabSession, t_s: float) -> None:
    """Step the paused session one step per tick until the scene's clock reaches t_s: exact times, as fast as the
    machine goes. (A running session steps at speed x real time instead, and catches up after a slow step.)"""
    while session.scene.time_s < t_s - 1e-9:
        session.single_step()  # a command, as every change: tick() applies the queued ones, then steps
        session.tick()


def report(session: LabSession, moment: str) -> None:
    scene = session.scene
    metrics = scene.metrics()
    blood, burn = metrics["bleeding"], metrics["cautery"]
    clearance = scene.tool_clearance_mm(BALL)
    where = "no tissue below" if clearance is None else f"{clearance:+.1f} mm from the tissue"
    print(f"t = {scene.time_s:4.1f} s {moment:28s} vessel {scene.bleed_rates()['vessel']:.4f} ml/s, "
          f"blood on the tissue {blood['on_surface_ml']:.3f} ml (suctioned {blood['suctioned_ml']:.3f} ml), "
          f"burn {burn['coagulation_depth_mm']:.2f} mm deep on {burn['coagulated_area_mm2']:.1f} mm^2; ball {where}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", default="auto", choices=ARCH_CHOICES)
    args = parser.parse_args()
    # overrides as --set texts; texture_size is one a rebuild applies, so it is given at the start
    session = LabSession(REPO_ROOT / "scenes" / "hemostasis.yaml", args.arch, overrides=("texture_size=128",))
    session.set_running(False)  # paused: play_until single-steps it
    print(f"{session.scene.name}: {len(session.parameters())} parameters, tools "
          f"{[tool.name for tool in session.scene.instruments]}, built in {session.build_seconds[-1][1]:.1f} s")

    play_until(session, 2.0)
    report(session, "(the vessel bleeds)")
    spec = session.parameters()[TIP].spec
    try:
        session.set_parameter(TIP, float("nan"))
    except Refused as exc:  # every command checks its values at once, as against a hostile browser
        print(f"refused: {exc}")
    used = session.set_parameter(TIP, 110.0)  # clamped into [spec.min, spec.max]; applied by the next tick
    print(f"tip temperature {session.scene.parameter_value(TIP):g} -> {used:g} {spec.unit} "
          f"(range {spec.min:g}-{spec.max:g})")
    vessel = session.scene.bleed_point("vessel").position_at(session.scene.time_s)
    session.set_resting(BALL, True)  # touch-the-tissue mode: lowered until REST_DEPTH_MM in
    session.take_over(BALL, vessel + [0.0, 0.0, 5.0])  # by hand, above the vessel (it leaves its script)
    session.set_energized(BALL, True)
    play_until(session, 2.1)
    report(session, "(ball on the vessel, on)")
    play_until(session, 2.5)
    report(session, "(after 0.4 s of contact)")
    play_until(session, 3.5)
    report(session, "(after 1.4 s of contact)")
    session.set_resting(BALL, False)
    session.take_over(BALL, vessel + [0.0, 0.0, 8.0])  # lifted, still held
    session.set_energized(BALL, False)
    play_until(session, 4.5)
    report(session, "(ball lifted, off)")
    if session.notice:
        print(f"session notice: {session.notice}")


if __name__ == "__main__":
    main()
