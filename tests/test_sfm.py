"""usp_jax.sfm: COLMAP's pixel convention, the pairs, the pose errors of a model and
the database, with pycolmap itself as the reference."""

import pathlib

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from usp_jax import sfm
from usp_jax.inference import threads as threads_module
from usp_jax.inference.features import Features
from usp_jax.inference.match_refinement import refine_matches


def test_colmap_keypoints_are_ours_plus_half_a_pixel_as_colmap_projects_the_optical_axis():
    height, width = 48, 64
    camera = pycolmap.Camera(
        model="PINHOLE", width=width, height=height, params=[50.0, 50.0, width / 2, height / 2]
    )
    # The optical axis meets the image at its centre: ((width - 1) / 2, (height - 1) / 2) in
    # ours (pixel centres at integers), (width / 2, height / 2) in COLMAP's.
    centre = np.array([[(width - 1) / 2, (height - 1) / 2]])
    np.testing.assert_allclose(sfm.colmap_keypoints(centre), [camera.img_from_cam([0, 0, 1])])
    np.testing.assert_array_equal(sfm.colmap_keypoints([[0, 0], [3, 2]]), [[0.5, 0.5], [3.5, 2.5]])


def test_image_pairs_every_pair_for_photos_and_a_window_for_video():
    np.testing.assert_array_equal(sfm.image_pairs(3), [[0, 1], [0, 2], [1, 2]])
    np.testing.assert_array_equal(sfm.image_pairs(4, window=1), [[0, 1], [1, 2], [2, 3]])
    np.testing.assert_array_equal(
        sfm.image_pairs(4, window=2), [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    )


def test_mixed_sizes_are_refused_naming_both_images_and_the_shared_camera():
    with pytest.raises(ValueError, match=r"b.png is 40x30.*one COLMAP camera"):
        sfm.check_sizes(["a.png", "b.png"], [(20, 40), (30, 40)])
    with pytest.raises(ValueError, match="two images or more, got 1"):
        sfm.check_sizes(["a.png"], [(20, 40)])


def _features(count: int, seed: int) -> Features:
    rng = np.random.default_rng(seed)
    keypoints = rng.uniform(0, 40, (count, 2)).astype(np.float32)
    return Features(keypoints, rng.random(count, np.float32), rng.random((count, 8), np.float32))


def _blank_images(folder, names, size=(48, 64)):
    folder.mkdir(parents=True)
    for name in names:
        cv2.imwrite(str(folder / name), np.zeros((*size, 3), np.uint8))
    return folder


def test_database_holds_the_keypoints_in_colmaps_convention_and_the_matches(tmp_path):
    names = ["a.png", "b.png", "c.png"]
    images = _blank_images(tmp_path / "images", names)
    features = [_features(n, seed) for seed, n in enumerate((30, 25, 20))]
    pairs = sfm.image_pairs(3)
    matches = sfm.match_pairs(features, pairs)
    ids = sfm.write_database(tmp_path / "db.db", images, names, features, pairs, matches)
    with pycolmap.Database.open(str(tmp_path / "db.db")) as db:
        assert db.num_images() == 3 and db.num_cameras() == 1
        for image_id, found in zip(ids, features):
            np.testing.assert_allclose(db.read_keypoints(image_id)[:, :2], found.keypoints + 0.5)
        for (i, j), pair_matches in zip(pairs, matches):
            np.testing.assert_array_equal(db.read_matches(ids[i], ids[j]), pair_matches)
        assert db.num_matches() == sum(len(m) for m in matches)


def test_the_database_camera_is_colmaps_guess_or_the_known_one_with_its_focal_as_a_prior(
    tmp_path,
):
    names = ["a.png", "b.png"]
    images = _blank_images(tmp_path / "images", names)
    features = [_features(10, seed) for seed in range(2)]
    pairs = sfm.image_pairs(2)
    matches = sfm.match_pairs(features, pairs)
    known = sfm.check_camera("PINHOLE", [70, 71, 32.5, 24])
    for name, camera in [("guess.db", sfm.Camera()), ("known.db", known)]:
        sfm.write_database(tmp_path / name, images, names, features, pairs, matches, camera)
    with pycolmap.Database.open(str(tmp_path / "guess.db")) as db:
        (guess,) = db.read_all_cameras()
    with pycolmap.Database.open(str(tmp_path / "known.db")) as db:
        (found,) = db.read_all_cameras()
    # COLMAP's own guess without EXIF: 1.2 x the longest side, the centre, no distortion.
    assert guess.model_name == "SIMPLE_RADIAL" and not guess.has_prior_focal_length
    np.testing.assert_allclose(guess.params, [1.2 * 64, 32, 24, 0])
    assert found.model_name == "PINHOLE" and found.has_prior_focal_length
    np.testing.assert_allclose(found.params, [70, 71, 32.5, 24])


@pytest.mark.parametrize(
    "model, params, message",
    [
        ("PINHOL", (), "'PINHOL' is not COLMAP's; one of SIMPLE_PINHOLE, PINHOLE,"),
        ("PINHOLE", (500, 500, 320), "PINHOLE takes 4 finite parameters \\(fx, fy, cx, cy"),
        ("SIMPLE_RADIAL", (-500, 320, 240, 0), "focal lengths positive\\), got -500.0"),
        ("PINHOLE", (500, float("nan"), 320, 240), "got 500.0, nan"),
    ],
    ids=["unknown-model", "too-few", "negative-focal", "nan"],
)
def test_a_camera_colmap_cannot_use_is_refused_naming_what_the_model_takes(model, params, message):
    with pytest.raises(ValueError, match=message):
        sfm.check_camera(model, params)


def _database_with_geometries(tmp_path, geometries):
    """A database of three blank images with two-view geometries {(id1, id2): (config, inliers)}."""
    names = ["a.png", "b.png", "c.png"]
    images = _blank_images(tmp_path / "images", names)
    database = tmp_path / "db.db"
    features = [_features(10, seed) for seed in range(3)]
    sfm.write_database(database, images, names, features, np.zeros((0, 2), int), [])
    with pycolmap.Database.open(str(database)) as db:
        for (id1, id2), (config, count) in geometries.items():
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = getattr(pycolmap.TwoViewGeometryConfiguration, config)
            geometry.inlier_matches = np.stack([np.arange(count)] * 2, axis=1).astype(np.uint32)
            db.write_two_view_geometry(id1, id2, geometry)
    return images, database


def test_the_mapper_starts_from_the_general_pair_with_most_inliers_never_a_planar_one(tmp_path):
    geometries = {
        (1, 2): ("PLANAR_OR_PANORAMIC", 9),
        (1, 3): ("CALIBRATED", 5),
        (2, 3): ("UNCALIBRATED", 6),
    }
    _, database = _database_with_geometries(tmp_path, geometries)
    assert sfm.initial_pair(database) == (2, 3)
    _, planar = _database_with_geometries(tmp_path / "planar", {(1, 2): ("PLANAR", 9)})
    assert sfm.initial_pair(planar) is None


class _Model:
    def __init__(self, registered, error):
        self.registered, self.error = registered, error

    def num_reg_images(self):
        return self.registered

    def compute_mean_reprojection_error(self):
        return self.error


@pytest.mark.parametrize(
    "from_general, from_colmap, kept, colmap_ran",
    [
        ([], [_Model(3, 0.5)], "colmap", True),  # the general start failed
        ([_Model(2, 0.3)], [_Model(3, 0.5)], "colmap", True),  # more images registered
        ([_Model(2, 0.3)], [_Model(2, 0.4)], "general", True),  # as many, lower error
        ([_Model(3, 0.3)], [], "general", False),  # every image: COLMAP's start never runs
    ],
)
def test_when_the_general_start_leaves_images_out_colmaps_own_start_runs_and_the_better_is_kept(
    tmp_path, monkeypatch, from_general, from_colmap, kept, colmap_ran
):
    images, database = _database_with_geometries(tmp_path, {(1, 3): ("CALIBRATED", 5)})
    starts = []

    def mapping(database, image_dir, folder, options, next_image_callback=None):
        general = options.init_image_id1 != -1
        assert options.init_num_trials == 1 or not general  # an unsuitable given pair: one try
        starts.append((options.init_image_id1, options.init_image_id2))
        (pathlib.Path(folder) / "0").mkdir(parents=True)
        (pathlib.Path(folder) / "0" / "from").write_text("general" if general else "colmap")
        for _ in range(2):  # two images registered in each run
            next_image_callback()
        return dict(enumerate(from_general if general else from_colmap))

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapping)
    counts = []
    models = sfm.map_images(database, images, tmp_path / "sparse", counts.append)
    assert starts == [(1, 3), (-1, -1)] if colmap_ran else starts == [(1, 3)]
    assert counts == ([1, 2, 1, 2] if colmap_ran else [1, 2])  # a progress bar starts over
    assert models == (from_general if kept == "general" else from_colmap)
    assert (tmp_path / "sparse" / "0" / "from").read_text() == kept
    assert sorted(p.name for p in tmp_path.iterdir() if "sparse" in p.name) == ["sparse"]


def test_tracks_refuse_the_weaker_match_that_would_put_two_keypoints_of_one_image_in_one():
    # Keypoint 0 of image 0 reaches keypoints 0 and 1 of image 1 (through image 2): connected
    # components would join all four; taken closest first, the last merges are refused.
    pairs = np.array([[0, 1], [0, 2], [1, 2]])
    matches = [np.array([[0, 0]]), np.array([[0, 0]]), np.array([[0, 0], [1, 0]])]
    distances = [np.array([0.1]), np.array([0.2]), np.array([0.3, 0.05])]
    nodes, track = sfm.keypoint_tracks([2, 2, 1], pairs, matches, distances)
    tracks = {tuple(map(tuple, nodes[track == t])) for t in range(track.max() + 1)}
    assert tracks == {((0, 0), (1, 0)), ((1, 1), (2, 0))}
    # In the given order instead, (0,0)-(1,0) and (0,0)-(2,0) come first and hold image 1's
    # keypoint 1 out: it is in no track.
    nodes, track = sfm.keypoint_tracks([2, 2, 1], pairs, matches)
    assert {tuple(map(tuple, nodes[track == t])) for t in range(track.max() + 1)} == {
        ((0, 0), (1, 0), (2, 0))
    }


def test_tracks_of_consistent_matches_are_their_connected_components():
    rng = np.random.default_rng(3)
    pairs = sfm.image_pairs(4)
    # 30 scene points; keypoint k of image i sees point perm[i][k]; each pair matches a random
    # half of the points, rightly: the tracks are the points seen in two images or more.
    perm = [rng.permutation(30) for _ in range(4)]
    inverse = [np.argsort(p) for p in perm]
    matches, seen = [], {}
    for i, j in pairs:
        points = rng.choice(30, 15, replace=False)
        matches.append(np.stack([inverse[i][points], inverse[j][points]], axis=1))
        for point in points:
            seen.setdefault(point, set()).update({(i, inverse[i][point]), (j, inverse[j][point])})
    distances = [rng.uniform(size=len(m)) for m in matches]
    nodes, track = sfm.keypoint_tracks([30] * 4, pairs, matches, distances)
    tracks = {frozenset(map(tuple, nodes[track == t])) for t in range(track.max() + 1)}
    assert tracks == {frozenset(members) for members in seen.values()}
    # Ordered by track, then image.
    assert np.all(np.diff(track) >= 0)
    same = track[1:] == track[:-1]
    assert np.all(np.diff(nodes[:, 0])[same] > 0)
    nodes, track = sfm.keypoint_tracks([2, 2], np.array([[0, 1]]), [np.zeros((0, 2))])
    assert nodes.shape == (0, 2) and track.shape == (0,)


def test_an_anchor_is_the_node_with_most_matches_then_the_highest_score():
    track = np.array([0, 0, 0, 1, 1])
    degree = np.array([1, 2, 2, 1, 1])
    scores = np.array([0.9, 0.1, 0.5, 0.2, 0.3])
    np.testing.assert_array_equal(sfm.track_anchors(track, degree, scores), [2, 4])


def test_fundamental_inliers_are_the_matches_a_fundamental_matrix_explains():
    rng = np.random.default_rng(0)
    world = rng.uniform([-2, -2, 4], [2, 2, 8], (80, 3))
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    turn = Rotation.from_euler("y", 8, degrees=True).as_matrix()
    views = [world @ K.T, (world @ turn.T + [0.5, 0.1, 0.0]) @ K.T]
    keypoints = [(v[:, :2] / v[:, 2:]).astype(np.float32) for v in views]
    features = [Features(k, np.ones(80, np.float32), np.zeros((80, 4))) for k in keypoints]
    right = np.stack([np.arange(60)] * 2, axis=1)
    wrong = np.stack([np.arange(60, 80), rng.permutation(np.arange(60, 80))], axis=1)
    matches = [np.concatenate([right, wrong])]
    kept = sfm.fundamental_inliers(features, np.array([[0, 1]]), matches)[0]
    kept, right_set = set(map(tuple, kept)), set(map(tuple, right))
    # A wrong match lying near its epipolar line by chance passes: no two-view test sees it.
    assert len(kept & right_set) >= 58 and len(kept - right_set) <= 2
    np.testing.assert_array_equal(
        sfm.fundamental_inliers(features, [[0, 1]], matches, None)[0], matches[0]
    )
    assert sfm.fundamental_inliers(features, [[0, 1]], [right[:7]])[0].shape == (0, 2)
    # Pairs on threads: each pair's own result, in the pairs' order.
    several = [matches[0], right[:7], right, matches[0][::-1]]
    threaded = sfm.fundamental_inliers(features, [[0, 1]] * 4, several)
    for pair_matches, found in zip(several, threaded):
        one = sfm.fundamental_inliers(features, [[0, 1]], [pair_matches])[0]
        np.testing.assert_array_equal(found, one)


def test_a_pair_opencvs_ransac_asserts_on_gets_no_matches_instead_of_ending_the_run(monkeypatch):
    # USAC's MAGSAC raised "!model.empty()" on one rendered pair's refined matches.
    def failing(*args):
        raise cv2.error("(-215:Assertion failed) !model.empty() in function 'setModelParameters'")

    monkeypatch.setattr(cv2, "findFundamentalMat", failing)
    features = [
        Features(np.random.default_rng(k).uniform(0, 99, (20, 2)), None, None) for k in (0, 1)
    ]
    matches = [np.stack([np.arange(20)] * 2, axis=1)]
    assert sfm.fundamental_inliers(features, [[0, 1]], matches)[0].shape == (0, 2)


def _shifted_views(shifts, size=(96, 128), seed=0):
    """Grey views [H, W] float32 of one smooth texture, view k shifted by shifts[k] (x, y): a
    point at p in view 0 lies at p + shifts[k] in view k."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, size).astype(np.float32), (0, 0), 1.5)
    return [
        cv2.warpAffine(
            texture,
            np.float32([[1, 0, dx], [0, 1, dy]]),
            size[::-1],
            flags=cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_REFLECT,
        )
        for dx, dy in shifts
    ]


def test_an_image_whose_matches_could_not_settle_keeps_them_all_and_the_others_only_settled():
    shifts = np.array([[0.0, 0.0], [1.3, -0.6], [-0.45, 2.2]])
    greys = _shifted_views(shifts)
    greys[2] = np.full_like(greys[2], 128.0)  # flat: no patch of view 2 can settle
    truth = np.random.default_rng(2).uniform(20, 76, (30, 2))
    features = [
        Features((truth + shift).astype(np.float32), np.full(30, 1.0 - k / 10), np.zeros(30))
        for k, shift in enumerate(shifts)
    ]
    matches = [np.stack([np.arange(30)] * 2, axis=1)] * 3
    _, kept, counts = sfm.refine_keypoints(greys, features, sfm.image_pairs(3), matches)
    assert counts["unchecked_images"] == 1
    np.testing.assert_array_equal(kept[1], matches[1])  # (0, 2): every match of view 2 kept
    np.testing.assert_array_equal(kept[2], matches[2])  # (1, 2)
    # (0, 1): only the matches that settled, which are all but view 1's unlucky few.
    assert counts["settled_matches"] == len(kept[0]) and 25 <= len(kept[0]) <= 30
    assert counts["kept_matches"] == len(kept[0]) + 60 and counts["matches"] == 90


def test_refinement_moves_keypoints_to_the_anchors_correspondence_and_the_database_holds_them(
    tmp_path,
):
    shifts = np.array([[0.0, 0.0], [1.3, -0.6], [-0.45, 2.2]])
    greys = _shifted_views(shifts)
    rng = np.random.default_rng(1)
    truth0 = rng.uniform(20, 76, (40, 2))  # (x, y) in view 0, away from the borders
    truth = [truth0 + shift for shift in shifts]
    angle = rng.uniform(0, 2 * np.pi, (3, 40))
    jitter = 0.7 * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    jitter[0] = 0  # view 0's points are exact and score highest: they anchor every track
    features = [
        Features((t + j).astype(np.float32), np.full(40, 1.0 - k / 10, np.float32), np.zeros(40))
        for k, (t, j) in enumerate(zip(truth, jitter))
    ]
    # A 41st keypoint of view 2, also matched to view 0's point 0.
    features[2] = Features(
        np.concatenate([features[2].keypoints, [[50.0, 50.0]]]).astype(np.float32),
        np.append(features[2].scores, 0.1),
        np.zeros(41),
    )
    pairs = sfm.image_pairs(3)
    same = np.stack([np.arange(40)] * 2, axis=1)
    matches = [same, np.concatenate([same, [[0, 40]]]), same]
    refined, kept, counts = sfm.refine_keypoints(greys, features, pairs, matches)
    # Keypoint 40 of view 2 would put a second keypoint of view 2 into track 0: refused.
    assert counts["tracks"] == 40 and counts["observations"] == 80 and counts["moved"] >= 72
    np.testing.assert_array_equal(refined[0].keypoints, features[0].keypoints)  # anchors stay
    for view in (1, 2):
        before = np.linalg.norm(features[view].keypoints[:40] - truth[view], axis=1)
        after = np.linalg.norm(refined[view].keypoints[:40] - truth[view], axis=1)
        assert np.median(before) > 0.6 and np.median(after) < 0.08 and after.max() < 0.15
    # COLMAP gets the matches whose two keypoints settled, never the refused one.
    for pair_matches, pair_kept in zip(matches, kept):
        assert set(map(tuple, pair_kept)) <= set(map(tuple, pair_matches)) - {(0, 40)}
        assert len(pair_kept) >= 36
    assert counts["settled_matches"] == counts["kept_matches"] == sum(map(len, kept))
    assert counts["matches"] == 121 and counts["unchecked_images"] == 0
    np.testing.assert_array_equal(refined[2].keypoints[40], [50.0, 50.0])
    images = tmp_path / "images"
    images.mkdir()
    names = [f"{k}.png" for k in range(3)]
    for name, grey in zip(names, greys):
        cv2.imwrite(str(images / name), grey.astype(np.uint8))
    ids = sfm.write_database(tmp_path / "db.db", images, names, refined, pairs, kept)
    with pycolmap.Database.open(str(tmp_path / "db.db")) as db:
        for image_id, found in zip(ids, refined):
            np.testing.assert_allclose(db.read_keypoints(image_id)[:, :2], found.keypoints + 0.5)
        for (i, j), pair_kept in zip(pairs, kept):
            np.testing.assert_array_equal(db.read_matches(ids[i], ids[j]), pair_kept)


@pytest.mark.parametrize("threads", [1, 3])
def test_an_image_whose_tracks_follow_two_anchor_images_refines_as_pair_by_pair(
    monkeypatch, threads
):
    monkeypatch.setattr(threads_module, "THREADS", threads)
    shifts = np.array([[0.0, 0.0], [1.3, -0.6], [-0.45, 2.2]])
    greys = _shifted_views(shifts)
    rng = np.random.default_rng(5)
    truth = rng.uniform(20, 76, (40, 2))
    scores = np.full((3, 40), 0.5, np.float32)
    scores[0, :20] = scores[1, 20:] = 1.0  # view 0 anchors tracks 0-19, view 1 tracks 20-39
    features = [
        Features(
            (truth + shift + rng.choice([-0.7, 0.7], (40, 2))).astype(np.float32), s, np.zeros(40)
        )
        for shift, s in zip(shifts, scores)
    ]
    matches = [np.stack([np.arange(40)] * 2, axis=1)] * 3
    refined, _, counts = sfm.refine_keypoints(greys, features, sfm.image_pairs(3), matches)
    expected = [f.keypoints.copy() for f in features]
    for anchor, view, tracks in ((0, 1, slice(0, 20)), (0, 2, slice(0, 20))) + (
        (1, 0, slice(20, 40)),
        (1, 2, slice(20, 40)),
    ):
        points, ok = refine_matches(
            greys[anchor],
            greys[view],
            features[anchor].keypoints[tracks],
            features[view].keypoints[tracks],
            affine_steps=sfm.tracks.AFFINE_STEPS,
        )
        expected[view][np.arange(40)[tracks][ok]] = points[ok]
    for found, want in zip(refined, expected):
        np.testing.assert_array_equal(found.keypoints, want)
    assert counts["observations"] == 80 and counts["moved"] >= 72


def test_models_come_largest_first_in_the_list_and_the_folders_whatever_colmaps_order(
    tmp_path, monkeypatch
):
    images, database = _database_with_geometries(tmp_path, {})
    built = [_Model(1, 0.2), _Model(3, 0.5), _Model(2, 0.3)]  # in COLMAP's order of building

    def mapping(database, image_dir, folder, options, next_image_callback=None):
        for k, model in enumerate(built):
            (pathlib.Path(folder) / str(k)).mkdir(parents=True)
            (pathlib.Path(folder) / str(k) / "images").write_text(str(model.registered))
        return dict(enumerate(built))

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapping)
    models = sfm.map_images(database, images, tmp_path / "sparse")
    assert [m.registered for m in models] == [3, 2, 1]
    written = {p.name: (p / "images").read_text() for p in (tmp_path / "sparse").iterdir()}
    assert written == {"0": "3", "1": "2", "2": "1"}
    with pytest.raises(ValueError, match="holds something already"):  # never mixes two runs
        sfm.map_images(database, images, tmp_path / "sparse")
    assert {p.name for p in (tmp_path / "sparse").iterdir()} == {"0", "1", "2"}


def test_mapping_never_writes_into_a_folder_a_killed_call_left_and_cleans_up_when_it_fails(
    tmp_path, monkeypatch
):
    images, database = _database_with_geometries(tmp_path, {})
    for left in ("sparse.start0", ".sparse.start0-killed"):  # what killed calls left
        (tmp_path / left / "7").mkdir(parents=True)

    def mapping(database, image_dir, folder, options, next_image_callback=None):
        assert not any(pathlib.Path(folder).iterdir())  # a fresh folder for every start
        (pathlib.Path(folder) / "0").mkdir()
        return {0: _Model(2, 0.2)}

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapping)
    sfm.map_images(database, images, tmp_path / "sparse")
    assert {p.name for p in (tmp_path / "sparse").iterdir()} == {"0"}

    def failing(database, image_dir, folder, options, next_image_callback=None):
        (pathlib.Path(folder) / "0").mkdir()
        raise KeyboardInterrupt

    monkeypatch.setattr(pycolmap, "incremental_mapping", failing)
    with pytest.raises(KeyboardInterrupt):
        sfm.map_images(database, images, tmp_path / "again")
    assert not list(tmp_path.glob("*again.start*")) and not (tmp_path / "again").exists()
