"""The look recomposes only the display tiles a change of the burn reaches (sims.look.display_tiles), and what it shows is
byte for byte what a full pass shows: while a tool burns, after a reset, on either heat grid, and with a stage that
shows the temperature (then every stepped tile changes the look, not only the damaged ones)."""
import numpy as np
import pytest

from sims.scene.config import REPO_ROOT


def full_pass(scene) -> list:
    """Base colour, normal and roughness maps of a pass over every tile."""
    scene.display_tiles.select_all()
    heat = None if scene.cautery is None else scene.heat_display
    return [scene.composer.compose(scene.display_tiles, heat, scene.film), *scene.composer.maps()]


def shown_maps(scene) -> list:
    return [scene.composite(), *scene.material_maps()]


HOT_GLOW = ("look.stages=[{name: healthy, texture: textures/liver_healthy.png}, {name: glow, texture: "
            "textures/liver_charred.png, field: temperature_c, from: 37.5, to: 60}]")


@pytest.mark.parametrize("divisor, look", [(1, None), (2, None), (1, HOT_GLOW)], ids=["heat-grid", "half-heat-grid", "temperature-stage"])
def test_recomposing_the_changed_tiles_shows_what_a_full_pass_shows(divisor, look):
    from sims.scene.assembly import Scene

    overrides = ["texture_size=128", f"cautery.heat_grid_divisor={divisor}"] + ([look] if look else [])
    scene = Scene.from_file(REPO_ROOT / "scenes" / "default.yaml", overrides)
    start = scene.composite()
    recomposed = []
    for _ in range(12):
        for _ in range(25):
            scene.step()
        shown = shown_maps(scene)
        recomposed.append(scene.display_tiles.listed)
        for name, partial, full in zip(("colour", "normal", "roughness"), shown, full_pass(scene)):
            assert np.array_equal(partial, full), f"{name} at t = {scene.time_s:.2f} s"
    tiles = scene.display_tiles.tiles
    assert 0 < max(recomposed) and min(recomposed) < tiles  # partial passes happened, and the burn was recomposed
    assert not np.array_equal(shown[0], start)  # the burn shows
    scene.reset()
    assert np.array_equal(scene.composite(), start), "after a reset the look is the look at t = 0"
    assert scene.display_tiles.listed == tiles


def test_an_idle_scene_recomposes_nothing():
    from sims.scene.assembly import Scene

    scene = Scene.from_file(REPO_ROOT / "scenes" / "default.yaml", ["texture_size=64", "instruments=[]"])
    for _ in range(20):  # the first step steps every tile once
        scene.step()
    first = scene.composite()
    for _ in range(20):
        scene.step()
    assert np.array_equal(scene.composite(), first) and scene.display_tiles.listed == 0
    assert scene.cautery.tiles.awake == 0


@pytest.mark.parametrize("scene_file, method", [("bleeding.yaml", "height_field"), ("bleeding.yaml", "particles"),
                                                ("hemostasis.yaml", "height_field")])
def test_recomposing_where_the_blood_changed_shows_what_a_full_pass_shows(scene_file, method):
    """Blood spreads, is sucked away, clots and leaves stains; the look recomposes only the tiles the film's touched
    tiles reach (sims.look.film, sims.look.display_tiles), every map equals a pass over every tile, and every texel that changed
    between two composites lies in a tile Scene.take_display_changes() names."""
    from sims.scene.assembly import Scene

    scene = Scene.from_file(REPO_ROOT / "scenes" / scene_file, ["texture_size=256", f"bleeding.method={method}"])
    written, before = [], shown_maps(scene)
    scene.take_display_changes()
    for _ in range(10):
        for _ in range(30):
            scene.step()
        shown = shown_maps(scene)
        written.append(scene.display_tiles.listed)
        tile, flags = scene.take_display_changes()  # what a texture stream compares: every changed texel is in it
        for old, new in zip(before, shown):
            differs = (old != new).reshape(old.shape[0], old.shape[1], -1).any(axis=-1)
            assert not (differs & ~np.kron(flags, np.ones((tile, tile), bool))[:differs.shape[0], :differs.shape[1]]).any()
        before = shown
        for name, partial, full in zip(("colour", "normal", "roughness"), shown, full_pass(scene)):
            assert np.array_equal(partial, full), f"{name} at t = {scene.time_s:.2f} s"
        scene.take_display_changes()  # the full pass wrote every tile (the same bytes): not a change to check
    assert 0 < max(written) and min(written) < scene.display_tiles.tiles  # partial passes, and blood was recomposed


def test_composing_only_the_wanted_tiles_shows_there_what_a_full_pass_shows():
    """Scene.composite(wanted), as the lab asks for the tiles its texture stream is about to read: two identical
    hemostasis scenes step together, one composes every tile, the other only a changing third of the tiles whose maps
    would change (pending_display_changes); in every wanted tile the maps are byte for byte the full pass's, the
    others keep what they showed, and a composite of everything afterwards catches up with the full pass."""
    from sims.scene.assembly import Scene

    overrides = ["texture_size=128"]
    full, lazy = (Scene.from_file(REPO_ROOT / "scenes" / "hemostasis.yaml", overrides) for _ in range(2))
    rng = np.random.default_rng(3)
    lazy_written, full_written, before = 0, 0, None
    for update in range(12):
        for _ in range(40):
            full.step()
            lazy.step()
        tile, pending = lazy.pending_display_changes()
        wanted = pending & (rng.random(pending.shape) < 1 / 3)
        shown = [lazy.composite((tile, wanted)), *lazy.material_maps()]
        lazy_written += lazy.display_tiles.listed
        truth = shown_maps(full)
        full_written += full.display_tiles.listed
        inside = np.kron(wanted, np.ones((tile, tile), bool))[:truth[0].shape[0], :truth[0].shape[1]]
        for name, partial, whole in zip(("colour", "normal", "roughness"), shown, truth):
            assert np.array_equal(partial[inside], whole[inside]), f"{name} in a wanted tile at t = {full.time_s:.2f} s"
        if before is not None:
            written = np.zeros(pending.size, bool)
            written[lazy.display_tiles.written] = True
            kept = ~np.kron(written.reshape(pending.shape), np.ones((tile, tile), bool))[:inside.shape[0], :inside.shape[1]]
            assert kept.any() and np.array_equal(shown[0][kept], before[kept]), "a tile that was not written changed"
        before = shown[0]
    assert lazy_written < full_written  # work waited
    for name, partial, whole in zip(("colour", "normal", "roughness"), shown_maps(lazy), shown_maps(full)):
        assert np.array_equal(partial, whole), f"{name} after catching up"


def test_blood_at_rest_that_clots_is_recomposed():
    """A pool whose depth stays while it clots (the height field's clot grows where blood rests): the film flags the
    tiles where the clot shown moved by CLOT_STEP or more, so the look darkens there; a smaller change flags nothing."""
    import taichi as ti

    from sims.look.film import CLOT_STEP, BloodFilm

    class Pool:  # a bleeding method with a film 0.5 mm deep everywhere, always moving
        film_shape, film_display, moved = (32, 32), None, True

        def __init__(self):
            self.film_clot = ti.field(ti.f32, self.film_shape)

        def fresh_film(self, out):
            out.fill(0.5)

    pool = Pool()
    film = BloodFilm(pool)
    film.advance(0.01, 1.0)
    film.take_touched()  # the pool appears
    film.advance(0.01, 1.0)
    assert not film.take_touched().any()  # at rest: nothing to recompose
    clot = np.zeros(Pool.film_shape, np.float32)
    clot[20:, 20:] = 0.5 * CLOT_STEP
    pool.film_clot.from_numpy(clot)
    film.advance(0.01, 1.0)
    assert not film.take_touched().any()
    clot[20:, 20:] = 0.5
    pool.film_clot.from_numpy(clot)
    film.advance(0.01, 1.0)
    touched = film.take_touched()
    assert touched[-1, -1] and not touched[0, 0]
    np.testing.assert_array_equal(film.clot.to_numpy(), clot)
