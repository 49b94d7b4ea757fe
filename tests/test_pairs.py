"""Tests of usp_jax.evaluation.pairs: HPatches layout, ground-truth homographies that register the images, errors."""

import cv2
import numpy as np
import pytest
import skimage.data

from usp_jax.evaluation.pairs import make_pairs, pair_rotations
from usp_jax.evaluation.zoom import pair_zooms, zoom_label, zoom_of

HEIGHT, WIDTH = 60, 80


def write_photo(path, rgb, size):
    """Writes an RGB photo resized to size (w, h), BGR on disk."""
    resized = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), cv2.cvtColor(resized, cv2.COLOR_RGB2BGR))


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """A textured photo, one smaller than the output (so it is enlarged), a broken file and a text file."""
    folder = tmp_path_factory.mktemp("photos")
    write_photo(folder / "astronaut.png", skimage.data.astronaut(), (160, 120))
    write_photo(folder / "chelsea.jpg", skimage.data.chelsea(), (40, 30))
    (folder / "broken.jpg").write_bytes(b"not an image")
    (folder / "notes.txt").write_text("ignored: not an image suffix")
    return folder


@pytest.fixture(scope="module")
def scenes(photos, tmp_path_factory):
    with pytest.warns(UserWarning, match="broken.jpg"):
        return make_pairs(photos, tmp_path_factory.mktemp("pairs"), size=(HEIGHT, WIDTH))


def read(path):
    return cv2.imread(str(path)).astype(np.float32) / 255.0


def turn_of(homography):
    """In-plane rotation (degrees, cv2.getRotationMatrix2D's sign) of H's Jacobian at image 1's centre."""
    centre, step = np.array([(WIDTH - 1) / 2, (HEIGHT - 1) / 2]), 1e-2
    moved = cv2.perspectiveTransform(
        np.array([[centre, centre + [step, 0], centre + [0, step]]]), homography
    )[0]
    jacobian = np.stack([moved[1] - moved[0], moved[2] - moved[0]], axis=1) / step
    return -np.degrees(np.arctan2(jacobian[1, 0] - jacobian[0, 1], jacobian[0, 0] + jacobian[1, 1]))


def assert_registered(scene, k, tolerance=0.03, coverage=0.3):
    """Image 1 warped by H_1_k with OpenCV is image k wherever image 1 covers it."""
    homography = np.loadtxt(scene / f"H_1_{k}")
    covered = cv2.warpPerspective(np.ones((HEIGHT, WIDTH), np.float32), homography, (WIDTH, HEIGHT))
    # Away from the edge of image 1's footprint, where bilinear weights mix in the black border.
    inside = cv2.erode((covered >= 1 - 1e-6).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(
        bool
    )
    assert inside.mean() > coverage
    warped = cv2.warpPerspective(read(scene / "1.ppm"), homography, (WIDTH, HEIGHT))
    error = np.abs(warped - read(scene / f"{k}.ppm"))[inside].mean()
    # Both images are resampled from the same photo: only interpolation differences remain.
    assert error < tolerance
    return homography, error, inside


def test_make_pairs_writes_hpatches_layout(scenes):
    assert [scene.name for scene in scenes] == [
        "v_astronaut",
        "i_astronaut",
        "v_chelsea",
        "i_chelsea",
    ]
    for scene in scenes:
        assert sorted(p.name for p in scene.iterdir()) == (
            [f"{k}.ppm" for k in range(1, 7)] + [f"H_1_{k}" for k in range(2, 7)]
        )
        for k in range(1, 7):
            assert cv2.imread(str(scene / f"{k}.ppm")).shape == (HEIGHT, WIDTH, 3)
        for k in range(2, 7):
            homography = np.loadtxt(scene / f"H_1_{k}")
            assert homography.shape == (3, 3) and homography[2, 2] == pytest.approx(1.0)


def test_viewpoint_homographies_register_image_1_onto_image_k(scenes):
    for scene in (s for s in scenes if s.name.startswith("v_")):
        first = read(scene / "1.ppm")
        for k in range(2, 7):
            homography = np.loadtxt(scene / f"H_1_{k}")
            target = read(scene / f"{k}.ppm")
            covered = cv2.warpPerspective(
                np.ones((HEIGHT, WIDTH), np.float32), homography, (WIDTH, HEIGHT)
            )
            # Away from the edge of image 1's footprint, where bilinear weights mix in the black border.
            inside = cv2.erode(
                (covered >= 1 - 1e-6).astype(np.uint8), np.ones((5, 5), np.uint8)
            ).astype(bool)
            assert inside.mean() > 0.3
            error = np.abs(cv2.warpPerspective(first, homography, (WIDTH, HEIGHT)) - target)[
                inside
            ].mean()
            # Both images are resampled from the same photo: only interpolation differences remain.
            assert error < 0.03
            nudged = np.array([[1, 0, 1.5], [0, 1, 1.5], [0, 0, 1]]) @ homography
            misregistered = np.abs(cv2.warpPerspective(first, nudged, (WIDTH, HEIGHT)) - target)[
                inside
            ]
            assert misregistered.mean() > 2 * error
            # The view is not image 1 itself: the homography is a real viewpoint change.
            assert np.abs(homography - np.eye(3)).max() > 0.05


def test_views_have_no_black_borders(tmp_path):
    bright = (100 + 0.6 * skimage.data.astronaut()).astype(
        np.uint8
    )  # no dark pixel in the photo itself
    # Larger than needed, so it is only shrunk (INTER_AREA, which cannot undershoot like cubic enlarging).
    write_photo(tmp_path / "bright.png", bright, (200, 200))
    for scene in make_pairs(tmp_path, tmp_path / "out", size=(HEIGHT, WIDTH), kinds=("v",)):
        for k in range(1, 7):
            # A pixel sampled even partly outside the photo would mix in the black border value.
            assert cv2.imread(str(scene / f"{k}.ppm")).min() >= 99


def test_illumination_scenes_keep_geometry_and_change_light(scenes):
    for scene in (s for s in scenes if s.name.startswith("i_")):
        first = read(scene / "1.ppm")
        np.testing.assert_array_equal(first, read(scene.parent / f"v_{scene.name[2:]}" / "1.ppm"))
        changes = []
        for k in range(2, 7):
            np.testing.assert_allclose(np.loadtxt(scene / f"H_1_{k}"), np.eye(3))
            image = read(scene / f"{k}.ppm")
            changes.append(np.abs(image - first).mean())
            # Same structure: the grey images stay strongly correlated.
            assert np.corrcoef(first.mean(-1).ravel(), image.mean(-1).ravel())[0, 1] > 0.6
        assert min(changes) > 0.01 and changes[-1] > changes[0]


def test_make_pairs_is_deterministic_for_a_seed(photos, scenes, tmp_path):
    with pytest.warns(UserWarning):
        again = make_pairs(photos, tmp_path / "again", size=(HEIGHT, WIDTH), kinds=("v",))
    with pytest.warns(UserWarning):
        other = make_pairs(photos, tmp_path / "other", size=(HEIGHT, WIDTH), kinds=("v",), seed=1)
    assert [s.name for s in again] == ["v_astronaut", "v_chelsea"]
    for scene in again:
        for name in ("2.ppm", "H_1_2"):
            assert (scene / name).read_bytes() == (
                scenes[0].parent / scene.name / name
            ).read_bytes()
    assert not np.allclose(np.loadtxt(other[0] / "H_1_2"), np.loadtxt(again[0] / "H_1_2"))


def test_missing_or_empty_sources_raise_naming_them(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        make_pairs(tmp_path / "nowhere", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="empty"):
        make_pairs(tmp_path / "empty", tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="ghost.png"):
        make_pairs([tmp_path / "ghost.png"], tmp_path / "out")


def test_unreadable_only_sources_raise(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"\x89PNG broken")
    with (
        pytest.warns(UserWarning, match="bad.png"),
        pytest.raises(FileNotFoundError, match="could be read"),
    ):
        make_pairs(tmp_path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_duplicate_scene_names_are_rejected_before_writing(photos, tmp_path):
    write_photo(tmp_path / "astronaut.jpg", skimage.data.astronaut(), (80, 60))
    with pytest.raises(ValueError, match="astronaut"):
        make_pairs([photos / "astronaut.png", tmp_path / "astronaut.jpg"], tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("views", [1, 7])
def test_views_outside_the_hpatches_layout_are_rejected_before_writing(photos, tmp_path, views):
    # The evaluation reads 1.ppm ... 6.ppm only: a 7th view would be written and never scored.
    with pytest.raises(ValueError, match="2 to 6"):
        make_pairs(photos, tmp_path / "out", num_views=views)
    assert not (tmp_path / "out").exists()


ANGLES = [90.0, 180.0, -90.0, 45.0, 135.0]


@pytest.fixture(scope="module")
def rotated(photos, tmp_path_factory):
    with pytest.warns(UserWarning, match="broken.jpg"):
        return make_pairs(
            photos,
            tmp_path_factory.mktemp("rotated"),
            size=(HEIGHT, WIDTH),
            kinds=("v",),
            rotation_angles=ANGLES,
        )


def test_rotated_pairs_register_image_1_onto_image_k_and_turn_by_the_listed_angles(rotated):
    # Indices in the source list, where broken.jpg holds position 1.
    for index, scene in zip((0, 2), rotated):
        turns = pair_rotations(index, 6, rotation_angles=ANGLES)
        assert sorted(turns) == sorted(ANGLES)  # five views, five angles: each once
        for k, turn in zip(range(2, 7), turns):
            homography, error, inside = assert_registered(scene, k)
            nudged = np.array([[1, 0, 1.5], [0, 1, 1.5], [0, 0, 1]]) @ homography
            misregistered = np.abs(
                cv2.warpPerspective(read(scene / "1.ppm"), nudged, (WIDTH, HEIGHT))
                - read(scene / f"{k}.ppm")
            )[inside]
            assert misregistered.mean() > 2 * error
            # The listed angle, give or take the view's own rotation (up to 6 (k - 1) degrees) and the
            # keystone's effect on the Jacobian.
            off = (turn_of(homography) - turn + 180) % 360 - 180
            assert abs(off) < 6 * (k - 1) + 10


def test_rotated_views_have_no_black_borders(tmp_path):
    bright = (100 + 0.6 * skimage.data.astronaut()).astype(np.uint8)
    write_photo(tmp_path / "bright.png", bright, (300, 300))  # only shrunk, as in the upright test
    for scene in make_pairs(
        tmp_path, tmp_path / "out", size=(HEIGHT, WIDTH), kinds=("v",), rotation=180
    ):
        for k in range(1, 7):
            assert cv2.imread(str(scene / f"{k}.ppm")).min() >= 99
        assert_registered(scene, 6)


def test_zoomed_pairs_register_show_no_black_border_and_zoom_by_the_drawn_factor(tmp_path):
    bright = (100 + 0.6 * skimage.data.astronaut()).astype(np.uint8)
    write_photo(tmp_path / "bright.png", bright, (300, 300))
    (scene,) = make_pairs(
        tmp_path, tmp_path / "out", size=(HEIGHT, WIDTH), kinds=("v",), zoom=(0.5, 2), seed=1
    )
    zooms = pair_zooms(0, 6, (0.5, 2), seed=1)
    for k, zoom in zip(range(2, 7), zooms):
        # The photo is enlarged with INTER_CUBIC, whose ringing dips a little below 100.
        assert cv2.imread(str(scene / f"{k}.ppm")).min() >= 90
        homography, _, _ = assert_registered(scene, k, tolerance=0.05, coverage=0.15)
        # The drawn zoom times the view's own scale change (up to 20 % and a keystone).
        assert 0.7 < zoom_of(homography, (HEIGHT, WIDTH)) / zoom < 1.4


def test_drawn_zooms_are_log_uniform_and_binned_in_steps_of_sqrt_2():
    drawn = np.log2([pair_zooms(i, 6, (0.5, 2), seed=3) for i in range(200)])
    assert drawn.min() >= -1 and drawn.max() <= 1
    assert np.histogram(drawn, bins=4, range=(-1, 1))[0].min() > 0.2 * drawn.size
    assert pair_zooms(0, 3, None) == [1.0, 1.0]
    labels = [zoom_label(z) for z in (0.5, 0.71, 0.9, 1.0, 1.2, 1.41, 2.5)]
    assert labels == ["<0.71", "0.71-1", "0.71-1", "1-1.41", "1-1.41", ">=1.41", ">=1.41"]
    shrink = np.diag([0.5, 0.5, 1.0])
    assert zoom_of(shrink, (HEIGHT, WIDTH)) == pytest.approx(0.5)


@pytest.mark.parametrize("zoom", [(0.1, 2), (2, 1), (0.5,)])
def test_bad_zooms_are_rejected_before_writing(photos, tmp_path, zoom):
    with pytest.raises(ValueError, match="zoom"):
        make_pairs(photos, tmp_path / "out", zoom=zoom)
    assert not (tmp_path / "out").exists()


def test_drawn_rotations_are_uniform_deterministic_and_listed_ones_serve_every_view_alike():
    drawn = np.array([pair_rotations(i, 6, seed=3, rotation=180) for i in range(200)])
    assert drawn.min() >= -180 and drawn.max() <= 180
    assert np.histogram(drawn, bins=4, range=(-180, 180))[0].min() > 0.2 * drawn.size
    assert pair_rotations(7, 6, seed=3, rotation=180) == drawn[7].tolist()
    assert pair_rotations(7, 6, seed=4, rotation=180) != drawn[7].tolist()
    assert pair_rotations(0, 6) == [0.0] * 5
    # Over as many photos as angles, each view k meets every angle once.
    listed = np.array([pair_rotations(i, 4, rotation_angles=[0, 90, 180]) for i in range(3)])
    assert all(sorted(column) == [0, 90, 180] for column in listed.T)


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(rotation=90, rotation_angles=[0, 90]), "not both"),
        (dict(rotation=200), r"\[0, 180\]"),
        (dict(rotation_angles=[0, 270]), r"\[-180, 180\]"),
        (dict(rotation_angles=[]), "one or more"),
    ],
)
def test_bad_rotations_are_rejected_before_writing(photos, tmp_path, changes, message):
    with pytest.raises(ValueError, match=message):
        make_pairs(photos, tmp_path / "out", **changes)
    assert not (tmp_path / "out").exists()
