import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage
from conftest import SMALL_FAST, SMALL_MODEL

from usp_jax.core.model import (
    CELL,
    ModelConfig,
    UnsuperPoint,
    bilinear_sample,
    describe,
    descriptor_neighbourhoods,
    fast_config,
    init_variables,
    l2_normalize,
    pad_descriptor_features,
    relative_to_pixels,
)

# conftest's small network with 8-dim descriptors.
SMALL = dataclasses.replace(SMALL_MODEL, descriptor_dim=8)


def apply(config, images):
    # Compiled whole: op-by-op dispatch of the network costs several times the compile.
    variables = init_variables(jax.random.PRNGKey(0), config)
    return jax.jit(UnsuperPoint(config).apply)(variables, images)


def test_outputs_have_one_point_per_cell_with_paper_ranges():
    images = jax.random.uniform(jax.random.PRNGKey(1), (2, 40, 56, 3))
    pred = apply(SMALL, images)
    m = (40 // 8) * (56 // 8)
    assert pred.scores.shape == (2, m)
    assert pred.relative.shape == pred.keypoints.shape == (2, m, 2)
    assert pred.descriptors.shape == (2, m, 8)
    assert 0 <= pred.scores.min() and pred.scores.max() <= 1
    assert 0 <= pred.relative.min() and pred.relative.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(pred.descriptors, axis=-1), 1.0, rtol=1e-5)


def test_position_mapping_is_paper_eq1_in_pixel_centre_coordinates():
    rel = np.random.default_rng(0).uniform(size=(3 * 4, 2)).astype(np.float32)
    xy = np.asarray(relative_to_pixels(jnp.asarray(rel), 3, 4))
    for r in range(3):
        for c in range(4):
            i = r * 4 + c
            # Paper eq. 1 gives edge coordinates; OpenCV centres are 0.5 px lower.
            assert xy[i, 0] == pytest.approx((c + rel[i, 0]) * 8 - 0.5)
            assert xy[i, 1] == pytest.approx((r + rel[i, 1]) * 8 - 0.5)
    # The cell centre (relative 0.5) is the mean of the cell's pixel centres 8c .. 8c + 7.
    centre = relative_to_pixels(jnp.full((1, 2), 0.5), 1, 1)
    np.testing.assert_allclose(centre, [[3.5, 3.5]])


def test_default_network_is_the_papers():
    variables = jax.eval_shape(init_variables, jax.random.PRNGKey(0))  # shapes, no compute
    kernels = [
        leaf.shape
        for path, leaf in jax.tree_util.tree_leaves_with_path(variables["params"])
        if path[-1].key == "kernel"
    ]
    out_channels = sorted(k[-1] for k in kernels)
    # 8 backbone convs, 3 heads of (256 -> 256) + (256 -> 1 | 2 | 256).
    assert sorted(out_channels) == sorted(
        [32, 32, 64, 64, 128, 128, 256, 256] + [256] * 3 + [1, 2, 256]
    )
    assert all(k[:2] == (3, 3) for k in kernels)


def reference_sample(feature_map, xy):
    """SciPy's order-1 spline with edge clamping, at feature coordinate (x + 0.5) / 8 - 0.5."""
    u = (xy[:, 0] + 0.5) / CELL - 0.5
    v = (xy[:, 1] + 0.5) / CELL - 0.5
    return np.stack(
        [
            scipy.ndimage.map_coordinates(feature_map[..., ch], [v, u], order=1, mode="nearest")
            for ch in range(feature_map.shape[-1])
        ],
        axis=-1,
    )


def test_bilinear_sampler_matches_scipy_including_borders():
    rng = np.random.default_rng(0)
    fmap = rng.normal(size=(5, 7, 3)).astype(np.float32)
    xy = rng.uniform([-0.5, -0.5], [7 * 8 - 0.5, 5 * 8 - 0.5], size=(200, 2)).astype(np.float32)
    np.testing.assert_allclose(
        bilinear_sample(jnp.asarray(fmap), jnp.asarray(xy)), reference_sample(fmap, xy), atol=1e-5
    )


def test_sampling_at_cell_centres_returns_the_coarse_entries():
    fmap = np.random.default_rng(1).normal(size=(3, 4, 2)).astype(np.float32)
    xy = relative_to_pixels(jnp.full((12, 2), 0.5), 3, 4)
    np.testing.assert_allclose(
        bilinear_sample(jnp.asarray(fmap), xy), fmap.reshape(12, 2), atol=1e-6
    )


def test_sampler_gradient_reaches_positions():
    fmap = jnp.asarray(np.random.default_rng(2).normal(size=(3, 4, 2)), jnp.float32)
    grad = jax.grad(lambda xy: bilinear_sample(fmap, xy).sum())(jnp.array([[10.0, 9.0]]))
    assert np.all(np.isfinite(grad)) and np.any(grad != 0)


def test_interpolation_off_reads_the_cell_descriptor():
    images = jax.random.uniform(jax.random.PRNGKey(3), (1, 16, 24, 3))
    on = apply(SMALL, images)
    off = apply(ModelConfig(**{**SMALL.__dict__, "interpolate_descriptors": False}), images)
    np.testing.assert_allclose(on.scores, off.scores)
    assert not np.allclose(on.descriptors, off.descriptors)


def _conv_then_sample(params, features, xy):
    """The dense reference: the descriptor head's last 3x3 "SAME" conv over the whole map
    (lax), then bilinear_sample at xy and L2 normalisation."""
    kernel, bias = params["descriptor"]["kernel"], params["descriptor"]["bias"]
    dense = jax.lax.conv_general_dilated(
        features[None], kernel, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )[0]
    return l2_normalize(bilinear_sample(dense + bias, xy))


@pytest.mark.parametrize("shape", [(3, 5), (1, 4), (4, 1), (2, 2)])
def test_descriptors_of_chosen_points_equal_the_convolved_map_sampled_there(shape):
    """Section 2.3's interpolated descriptor from the last conv's interpolated input
    neighbourhoods: inside, between, on and beyond the border cells, and 1-cell-wide maps."""
    rng = np.random.default_rng(len(shape) + shape[0])
    h, w = shape
    features = jnp.asarray(rng.normal(size=(h, w, 6)), jnp.float32)
    params = {
        "descriptor": {
            "kernel": jnp.asarray(rng.normal(size=(3, 3, 6, 5)), jnp.float32),
            "bias": jnp.asarray(rng.normal(size=5), jnp.float32),
        }
    }
    xy = jnp.asarray(
        np.concatenate(
            [rng.uniform(-12, [8 * w + 12, 8 * h + 12], size=(40, 2)), [[3.5, 3.5], [-0.5, -0.5]]]
        ),
        jnp.float32,
    )
    padded = pad_descriptor_features(features[None])[0]
    got = describe(params, descriptor_neighbourhoods(padded, xy, h, w))
    np.testing.assert_allclose(got, _conv_then_sample(params, features, xy), atol=1e-5)


def test_descriptors_of_points_on_several_maps_come_from_one_buffer():
    """A pyramid's levels: each point reads its own map, by its size and first row."""
    rng = np.random.default_rng(3)
    maps = [jnp.asarray(rng.normal(size=(h, w, 4)), jnp.float32) for h, w in ((3, 4), (2, 3))]
    params = {
        "descriptor": {
            "kernel": jnp.asarray(rng.normal(size=(3, 3, 4, 3)), jnp.float32),
            "bias": jnp.zeros(3),
        }
    }
    padded = [pad_descriptor_features(m[None])[0] for m in maps]
    xy = jnp.asarray(rng.uniform(0, 24, size=(10, 2)), jnp.float32)
    level = np.arange(10) % 2
    heights, widths = np.array([3, 2])[level], np.array([4, 3])[level]
    offsets = np.array([0, len(padded[0])])[level]
    neighbourhoods = descriptor_neighbourhoods(
        jnp.concatenate(padded), xy, jnp.asarray(heights), jnp.asarray(widths), offsets
    )
    got = describe(params, neighbourhoods)
    for i in range(2):
        want = _conv_then_sample(params, maps[i], xy[level == i])
        np.testing.assert_allclose(got[level == i], want, atol=1e-5)


@pytest.mark.parametrize("config", [SMALL, SMALL_FAST], ids=["vgg", "fast"])
def test_a_sparse_network_returns_the_features_its_descriptors_are_computed_from(config):
    images = jax.random.uniform(jax.random.PRNGKey(4), (2, 32, 48, 3))
    variables = init_variables(jax.random.PRNGKey(0), config)
    dense = jax.jit(UnsuperPoint(config).apply)(variables, images)
    sparse_apply = jax.jit(UnsuperPoint(config, sparse_descriptors=True).apply)
    predictions, features, anchors = sparse_apply(variables, images)
    assert predictions.descriptors is None and features.shape[:3] == (2, 4, 6)
    np.testing.assert_array_equal(predictions.scores, dense.scores)
    np.testing.assert_array_equal(anchors, dense.keypoints)  # interpolated: read at the points
    padded = pad_descriptor_features(features)
    for b in range(2):
        neighbourhoods = descriptor_neighbourhoods(padded[b], dense.keypoints[b], 4, 6)
        got = describe(variables["params"], neighbourhoods)
        np.testing.assert_allclose(got, dense.descriptors[b], atol=1e-5)


@pytest.mark.parametrize("shape", [(1, 30, 32, 3), (1, 32, 4, 3), (32, 32, 3)])
def test_bad_input_shape_is_a_clear_error(shape):
    with pytest.raises(ValueError, match="multiple of 8|expected images"):
        apply(SMALL, jnp.zeros(shape))


def test_bfloat16_compute_keeps_float32_outputs():
    images = jax.random.uniform(jax.random.PRNGKey(4), (1, 16, 16, 3))
    pred = apply(ModelConfig(**{**SMALL.__dict__, "dtype": "bfloat16"}), images)
    assert pred.scores.dtype == jnp.float32 and pred.descriptors.dtype == jnp.float32


@pytest.mark.parametrize("height, width", [(32, 48), (40, 56)])  # even and odd cell grids
def test_fast_backbone_keeps_one_point_per_cell_and_the_paper_ranges(height, width):
    images = jax.random.uniform(jax.random.PRNGKey(5), (2, height, width, 3))
    pred = apply(SMALL_FAST, images)
    m = (height // 8) * (width // 8)
    assert pred.scores.shape == (2, m) and pred.descriptors.shape == (2, m, 8)
    assert 0 <= pred.relative.min() and pred.relative.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(pred.descriptors, axis=-1), 1.0, rtol=1e-5)


def test_fast_network_is_translation_equivariant_in_whole_cells_away_from_the_border():
    # Content shifted by one cell gives the same scores, positions and descriptors one cell over,
    # wherever the receptive field (about 60 px with the heads) sees no padding. An earlier
    # version with a 1/16 level failed this and learned descriptors of where a cell sits in the
    # crop instead of what it shows (experiments/notes/choices.md, "The fast network").
    big = jax.random.uniform(jax.random.PRNGKey(8), (1, 168, 200, 3))
    a, b = apply(SMALL_FAST, big[:, :160, :192]), apply(SMALL_FAST, big[:, 8:, 8:])
    margin = 8  # cells: 64 px, more than the receptive field's radius

    def inner(leaf, offset):
        grid = leaf.reshape(20, 24, -1)
        return grid[margin + offset : 20 - margin + offset, margin + offset : 24 - margin + offset]

    for name in ("scores", "relative", "descriptors"):
        np.testing.assert_allclose(
            inner(getattr(a, name), 1), inner(getattr(b, name), 0), atol=1e-5, err_msg=name
        )


def test_fast_network_gradients_reach_every_parameter():
    images = jax.random.uniform(jax.random.PRNGKey(6), (2, 32, 48, 3))
    variables = init_variables(jax.random.PRNGKey(0), SMALL_FAST)
    model = UnsuperPoint(SMALL_FAST)

    @jax.jit
    def grads(params):
        def loss(params):
            pred, _ = model.apply(
                {**variables, "params": params}, images, train=True, mutable=["batch_stats"]
            )
            # Distinct weights per output, so that no BatchNorm'd sum is constant.
            weights = [jnp.linspace(-1.0, 2.0, leaf.size).reshape(leaf.shape) for leaf in pred]
            return sum(jnp.sum(w * leaf) for w, leaf in zip(weights, pred))

        return jax.grad(loss)(params)

    flat = jax.tree_util.tree_leaves_with_path(grads(variables["params"]))
    for path, grad in flat:
        assert np.all(np.isfinite(grad)), path
        assert np.any(grad != 0), f"no gradient reaches {jax.tree_util.keystr(path)}"
    # The full-resolution patch conv and the residual blocks train too.
    names = " ".join(jax.tree_util.keystr(path) for path, _ in flat)
    assert "backbone" in names and len(flat) > 30


def test_fast_network_is_a_fraction_of_the_papers_parameters():
    def count(config):
        shapes = jax.eval_shape(init_variables, jax.random.PRNGKey(0), config)
        return sum(np.prod(leaf.shape) for leaf in jax.tree.leaves(shapes["params"]))

    assert count(fast_config()) < count(ModelConfig()) / 3


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"backbone": "resnet"}, "backbone must be one of vgg, fast"),
        ({"backbone": "fast"}, "needs 4 entries"),
        ({"backbone_channels": (8, 8, 8, 8)}, "needs 8 entries"),
    ],
)
def test_a_backbone_name_or_width_list_that_does_not_fit_is_a_clear_error(changes, message):
    with pytest.raises(ValueError, match=message):
        ModelConfig(**changes)
