"""A burn headless: the ball electrode of scenes/default.yaml rested on the liver and held there, switched on, for
HOLD_S seconds at two tip temperatures; prints the coagulation depth (mm) and area (mm^2) each leaves.

Run: python examples/burn_depth.py [--arch cpu|gpu|auto]   (about 5 s on 2 CPU cores once the kernels are cached)
"""
import argparse

from sims.core.backend import ARCH_CHOICES
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT

HOLD_S = 2.0                 # s the ball is held on, energized
SPOT_MM = (0.0, 4.7, 8.0)    # above the middle of the patch; lowered from here until it touches
TIPS_C = (120.0, 250.0)      # tip temperatures compared
BALL = "ball_electrode"


def burn(scene: Scene, tip_c: float) -> dict:
    """Back to t = 0 (fresh tissue), the ball at tip_c resting 0.3 mm deep under SPOT_MM for HOLD_S: cautery metrics."""
    scene.reset()  # also gives every tool back to its script: the hand takes them again below
    scene.set_parameter(f"instruments.{BALL}.tip_temperature_c", tip_c)
    scene.rest_on_tissue(BALL, SPOT_MM, depth_mm=0.3)
    scene.set_energized(BALL, True)
    scene.set_energized("spatula", False)  # the scene's script presses the spatula at t = 1 s: keep it off
    for _ in range(round(HOLD_S / scene.time_step_s)):
        scene.step()
    return scene.metrics()["cautery"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", default="auto", choices=ARCH_CHOICES)
    args = parser.parse_args()
    # 256 texels a side instead of the scene's 512: a quarter of the work, and the burn is still many texels wide
    scene = Scene.from_file(REPO_ROOT / "scenes" / "default.yaml", overrides=["texture_size=256"], arch=args.arch)
    print(f"{scene.name} on {scene.arch}: ball {scene.instrument(BALL).shape['radius_mm']} mm radius, "
          f"held {HOLD_S:g} s, heat grid {scene.heat_surface.mask.shape[0]}^2 texels")
    for tip_c in TIPS_C:
        cautery = burn(scene, tip_c)
        print(f"tip {tip_c:5.0f} C: coagulation depth {cautery['coagulation_depth_mm']:.2f} mm, "
              f"coagulated area {cautery['coagulated_area_mm2']:.1f} mm^2, "
              f"charred {cautery['charred_area_mm2']:.1f} mm^2, tissue at {cautery['max_temperature_c']:.0f} C at most")


if __name__ == "__main__":
    main()
