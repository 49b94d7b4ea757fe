"""Host input pipeline: sources, decoding, crops, determinism, sharding and bad input."""

import dataclasses
import logging
import re

import cv2
import numpy as np
import pytest
import tensorflow_datasets as tfds

from usp_jax.inference import images
from usp_jax.training import crops, data

SMALL = dict(height=48, width=64, num_workers=2, prefetch=2)


def _write(path, image):
    """Writes an OpenCV-ordered (BGR/BGRA/gray) array, making parent folders."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)
    return path


def _photo_folder(root, count=5, shape=(60, 80)):
    """``count`` random colour PNGs of ``shape``."""
    rng = np.random.default_rng(0)
    for i in range(count):
        image = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
        _write(root / f"img{i}.png", image)
    return root


def test_folder_source_finds_nested_files_of_mixed_extensions_and_case(tmp_path):
    image = np.full((8, 8, 3), 100, np.uint8)
    names = ["a.JPG", "sub/b.png", "sub/deeper/c.Jpeg", "d.tiff", "e.webp", "f.BMP"]
    for name in names:
        _write(tmp_path / name, image)
    (tmp_path / "notes.txt").write_text("not an image")
    source = data.open_source(str(tmp_path))
    found = sorted(str(p.relative_to(tmp_path)) for p in source.paths)
    assert found == sorted(names)
    assert all(source[i].shape == (8, 8, 3) for i in range(len(source)))


@pytest.mark.parametrize(
    "stored, expected_rgb",
    [
        # Grayscale is replicated to three channels.
        (np.array([[0, 128], [255, 7]], np.uint8), [[[0] * 3, [128] * 3], [[255] * 3, [7] * 3]]),
        # BGR file order becomes RGB.
        (np.array([[[1, 2, 3]]], np.uint8), [[[3, 2, 1]]]),
        # Alpha is dropped, colour kept as stored (not premultiplied).
        (
            np.array([[[10, 20, 30, 0], [40, 50, 60, 255]]], np.uint8),
            [[[30, 20, 10], [60, 50, 40]]],
        ),
        # 16-bit gray scales 65535 -> 255.
        (np.array([[0, 257 * 200, 65535]], np.uint16), [[[0] * 3, [200] * 3, [255] * 3]]),
        # 16-bit colour.
        (np.array([[[0, 257 * 20, 65535]]], np.uint16), [[[255, 20, 0]]]),
    ],
    ids=["gray", "bgr", "rgba", "gray16", "bgr16"],
)
def test_decode_gives_uint8_rgb_with_known_values(tmp_path, stored, expected_rgb):
    path = _write(tmp_path / "x.png", stored)
    image = images.read_image(path)
    assert image.dtype == np.uint8
    np.testing.assert_array_equal(image, np.array(expected_rgb, np.uint8))


def test_decode_garbage_is_a_one_line_error_naming_it():
    with pytest.raises(ValueError, match="bad.jpg") as error:
        images.decode_image(b"not an image", "bad.jpg")
    assert "\n" not in str(error.value)


def test_random_crop_shape_and_determinism():
    image = np.random.default_rng(0).integers(0, 256, (100, 150, 3), dtype=np.uint8)
    crop = lambda seed: crops.random_crop(np.random.default_rng(seed), image, 48, 64, (0.3, 1.0))
    assert crop(0).shape == (48, 64, 3) and crop(0).dtype == np.uint8
    np.testing.assert_array_equal(crop(0), crop(0))
    assert not np.array_equal(crop(0), crop(1))


def test_random_crop_of_an_image_the_size_of_the_crop_is_the_image():
    image = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    np.testing.assert_array_equal(crops.random_crop(np.random.default_rng(3), image, 48, 64), image)


def test_random_crop_never_shrinks_the_window_below_the_output():
    # scale 0.25 of a 2x image asks for a window half the output: raised to exactly the output
    # size, the crop is then an unresampled sub-array.
    image = np.random.default_rng(0).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    crop = crops.random_crop(np.random.default_rng(5), image, 48, 64, (0.25, 0.25))
    windows = np.lib.stride_tricks.sliding_window_view(image, (48, 64, 3))[..., 0, :, :, :]
    assert (windows == crop).all(axis=(-3, -2, -1)).any()


def test_random_crop_upscales_a_small_image():
    # 20x30 into 48x64: the largest 3:4 window is 20x27, enlarged bilinearly.
    image = np.tile(np.arange(30, dtype=np.uint8) * 8, (20, 1))[..., None].repeat(3, axis=2)
    crop = crops.random_crop(np.random.default_rng(0), image, 48, 64)
    candidates = [
        cv2.resize(image[:, left : left + 27], (64, 48), interpolation=cv2.INTER_LINEAR)
        for left in range(30 - 27 + 1)
    ]
    assert any(np.array_equal(crop, c) for c in candidates)


def _coordinate_photo(rows=200, cols=250):
    """A photo whose red channel is its x and green its y coordinate (both < 256): resampling a
    linear ramp keeps it linear, so a window's pixels tell which photo point they show."""
    ys, xs = np.mgrid[0:rows, 0:cols]
    return np.stack([xs, ys, np.full_like(xs, 100)], -1).astype(np.uint8)


@pytest.mark.parametrize("scale_range", [(0.3, 0.6), (1.0, 1.0)])
def test_context_crop_shows_the_photo_at_one_scale_around_a_crop_inside_it(scale_range):
    photo = _coordinate_photo()
    side = crops.context_side(48, 64)
    assert side == 80  # the crop's diagonal
    for seed in range(3):
        window = crops.random_context_crop(np.random.default_rng(seed), photo, 48, 64, scale_range)
        assert window.shape == (side, side, 4) and window.dtype == np.uint8
        valid = window[..., 3] == 255
        assert set(np.unique(window[..., 3])) <= {0, 255}
        # The crop at the window's centre lies inside the photo.
        assert valid[16:64, 8:72].all()
        # Photo point = offset + step * window pixel, one step on both axes (no stretch).
        v, u = np.nonzero(valid)
        fit_x = np.polyfit(u, window[..., 0][valid].astype(float), 1)
        fit_y = np.polyfit(v, window[..., 1][valid].astype(float), 1)
        assert fit_x[0] == pytest.approx(fit_y[0], rel=0.02)
        # Within rounding to uint8 and the shrink-then-warp resampling.
        assert np.abs(np.polyval(fit_x, u) - window[..., 0][valid]).max() < 1.5
        # Padding is black, and only where the window reaches past the photo.
        assert (window[~valid] == 0).all()
        x = np.polyval(fit_x, np.arange(side))[None, :]
        y = np.polyval(fit_y, np.arange(side))[:, None]
        beyond = (x < -1) | (x > 249 + 1) | (y < -1) | (y > 199 + 1)
        well_inside = (x > 1) & (x < 249 - 1) & (y > 1) & (y < 199 - 1)
        assert not valid[beyond].any() and valid[well_inside].all()
        if scale_range == (1.0, 1.0):
            # The crop spans the photo's height, so its square window must be padded.
            assert not valid.all()
        else:
            assert valid.all()


def test_context_window_batches_are_windows_and_switched_off_they_are_the_crops(tmp_path):
    config = data.DataConfig(source=str(_photo_folder(tmp_path, shape=(120, 160))), **SMALL)
    windows = dataclasses.replace(config, context_window=True)
    assert config.example_shape == (48, 64, 3) and windows.example_shape == (80, 80, 4)
    assert data.make_dataset(windows, 3, seed=0)[1].shape == (3, 80, 80, 4)
    assert data.make_dataset(config, 3, seed=0)[1].shape == (3, 48, 64, 3)


@pytest.mark.parametrize("policy, small_seen", [("upscale", True), ("skip", False)])
def test_small_images_policy(tmp_path, policy, small_seen):
    _write(tmp_path / "big1.png", np.full((60, 80, 3), (0, 255, 0), np.uint8))
    _write(tmp_path / "big2.png", np.full((60, 80, 3), (255, 0, 0), np.uint8))
    _write(tmp_path / "small.png", np.full((20, 30, 3), (0, 0, 255), np.uint8))  # Red in RGB.
    config = data.DataConfig(source=str(tmp_path), small_images=policy, **SMALL)
    dataset = data.make_dataset(config, 6, seed=0)
    crops = np.concatenate([dataset[step] for step in range(2)])
    assert crops.shape == (12, 48, 64, 3)
    red = (crops == (255, 0, 0)).all(axis=(1, 2, 3))
    assert red.any() == small_seen
    assert data.stats(dataset)["skipped_images"] == (0 if small_seen else 1)


def test_dataset_is_deterministic_and_resumes_exactly(tmp_path):
    config = data.DataConfig(source=str(_photo_folder(tmp_path)), **SMALL)
    full = data.iterate(data.make_dataset(config, 3, seed=7))
    expected = [next(full) for _ in range(6)]
    resumed = data.iterate(data.make_dataset(config, 3, seed=7), start_step=3)
    for step in range(3, 6):
        np.testing.assert_array_equal(next(resumed), expected[step])
    assert expected[0].shape == (3, 48, 64, 3) and expected[0].dtype == np.uint8
    other_seed = data.make_dataset(config, 3, seed=8)[0]
    assert not np.array_equal(other_seed, expected[0])


def test_process_slices_partition_the_global_batch(tmp_path):
    config = data.DataConfig(source=str(_photo_folder(tmp_path)), **SMALL)
    single = data.make_dataset(config, 6, seed=1)
    shards = [
        data.make_dataset(config, 2, seed=1, process_index=p, process_count=3) for p in range(3)
    ]
    for step in (0, 4):
        np.testing.assert_array_equal(np.concatenate([s[step] for s in shards]), single[step])


def test_batches_of_one_image_are_the_crops_of_larger_batches(tmp_path):
    config = data.DataConfig(source=str(_photo_folder(tmp_path)), **SMALL)
    ones = data.iterate(data.make_dataset(config, 1, seed=2))
    pairs = data.make_dataset(config, 2, seed=2)
    singles = np.concatenate([next(ones) for _ in range(4)])
    np.testing.assert_array_equal(singles, np.concatenate([pairs[0], pairs[1]]))


def test_corrupt_file_is_skipped_with_one_warning_and_counted(tmp_path, caplog):
    _photo_folder(tmp_path, count=3)
    (tmp_path / "broken.jpg").write_bytes(b"\x00garbage" * 10)
    config = data.DataConfig(source=str(tmp_path), **SMALL)
    dataset = data.make_dataset(config, 4, seed=0)
    with caplog.at_level(logging.WARNING, logger="usp_jax.training.data"):
        batches = [dataset[step] for step in range(3)]  # 12 crops: every file, several times.
    assert all(b.shape == (4, 48, 64, 3) for b in batches)
    warnings = [r.getMessage() for r in caplog.records if "broken.jpg" in r.getMessage()]
    assert len(warnings) == 1
    assert data.stats(dataset) == {"skipped_images": 1}


def test_source_without_a_readable_image_fails_at_once(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"garbage")
    (tmp_path / "b.png").write_bytes(b"")
    with pytest.raises(ValueError, match=re.escape(str(tmp_path))):
        data.make_dataset(data.DataConfig(source=str(tmp_path), **SMALL), 2, seed=0)


def test_empty_or_missing_folder_is_a_one_line_error_naming_it(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no images here")
    with pytest.raises(ValueError, match="empty") as error:
        data.open_source(str(tmp_path / "empty"))
    assert "\n" not in str(error.value)
    with pytest.raises(FileNotFoundError, match="nowhere") as error:
        data.open_source(str(tmp_path / "nowhere"))
    assert "\n" not in str(error.value)


def test_sample_source_holds_real_photos():
    source = data.open_source("sample")
    assert len(source) >= 10
    for i in range(len(source)):
        image = source[i]
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
        assert min(image.shape[:2]) >= 150 and image.std() > 10, source.name(i)


class Coco(tfds.core.GeneratorBasedBuilder, skip_registration=True):
    """A three-image stand-in for TFDS ``coco/2017``: its name, config, version, nested features.

    TFDS's own coco builder touches TensorFlow in ``_info``, so ``tfds.data_source("coco/2017")``
    fails without TensorFlow even when the files are prepared; ``open_source`` must not.
    """

    VERSION = tfds.core.Version("1.1.0")
    BUILDER_CONFIGS = [tfds.core.BuilderConfig(name="2017")]

    def _info(self):
        features = tfds.features.FeaturesDict(
            {
                # PNG, not COCO's JPEG, so that pixels compare exactly.
                "image": tfds.features.Image(shape=(None, None, 3), encoding_format="png"),
                "image/id": np.int64,
                "objects": tfds.features.Sequence(
                    {
                        "bbox": tfds.features.BBoxFeature(),
                        "label": tfds.features.ClassLabel(num_classes=80),
                    }
                ),
            }
        )
        return tfds.core.DatasetInfo(builder=self, features=features)

    def _split_generators(self, dl_manager):
        return {"train": self._generate_examples()}

    def _generate_examples(self):
        # Encoded bytes, as the real builder passes files: encoding arrays needs TensorFlow.
        for key, image in enumerate(_tfds_images()):
            objects = {"bbox": np.array([[0.1, 0.2, 0.5, 0.6]], np.float32), "label": [key]}
            encoded = cv2.imencode(".png", image)[1].tobytes()
            yield key, {"image": encoded, "image/id": key, "objects": objects}


def _tfds_images():
    """OpenCV-ordered images: two BGR, one grayscale (COCO holds some)."""
    rng = np.random.default_rng(0)
    return [
        rng.integers(0, 256, (50, 70, 3), dtype=np.uint8),
        rng.integers(0, 256, (60, 64), dtype=np.uint8),
        rng.integers(0, 256, (48, 90, 3), dtype=np.uint8),
    ]


@pytest.fixture(scope="module")
def tfds_dir(tmp_path_factory):
    """A data dir holding coco/2017 prepared in array_record, without TensorFlow."""
    data_dir = tmp_path_factory.mktemp("tfds")
    Coco(data_dir=str(data_dir), config="2017", file_format="array_record").download_and_prepare()
    return str(data_dir)


def test_tfds_source_reads_prepared_array_record_images(tfds_dir):
    source = data.open_source("tfds:coco/2017", tfds_data_dir=tfds_dir)
    assert len(source) == 3
    # Read back as RGB; the writer shuffles records.
    expected = [
        im[..., ::-1] if im.ndim == 3 else np.repeat(im[..., None], 3, 2) for im in _tfds_images()
    ]
    got = [source[i] for i in range(len(source))]
    assert sorted(x.tobytes() for x in got) == sorted(x.tobytes() for x in expected)
    config = data.DataConfig(source="tfds:coco/2017:train", tfds_data_dir=tfds_dir, **SMALL)
    assert data.make_dataset(config, 4, seed=0)[1].shape == (4, 48, 64, 3)


def test_unknown_tfds_name_or_split_is_a_one_line_error_naming_it(tfds_dir):
    with pytest.raises(ValueError, match="no_such_dataset") as error:
        data.open_source("tfds:no_such_dataset", tfds_data_dir=tfds_dir)
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="coco/2017:test") as error:
        data.open_source("tfds:coco/2017:test", tfds_data_dir=tfds_dir)
    assert "\n" not in str(error.value)


def test_decode_applies_the_exif_orientation_like_cv2_imread():
    import io

    import PIL.Image

    stored = np.zeros((20, 40, 3), np.uint8)
    stored[:, :20] = (255, 0, 0)  # red left half as stored
    image = PIL.Image.fromarray(stored)
    exif = image.getexif()
    exif[0x0112] = 6  # Orientation: the viewer turns it 90 degrees clockwise
    encoded = io.BytesIO()
    image.save(encoded, "JPEG", exif=exif, quality=95)
    decoded = images.decode_image(encoded.getvalue())
    assert decoded.shape == (40, 20, 3)  # upright as displayed: the red half is now on top
    assert decoded[:18].mean(axis=(0, 1))[0] > 240 and decoded[22:].max() < 16
