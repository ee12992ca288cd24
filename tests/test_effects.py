"""Camera effects: identity, determinism, noise level, vignetting, blur without shifts, config keys."""

import numpy as np
import pytest

from surftrack.synth.effects import CameraEffects, apply_effects, motion_blur_kernel, vignetting_gain


def textured(h=96, w=128, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def centroid(img):
    g = img.astype(np.float64).sum(axis=2)
    g = g - np.median(g)
    g[g < 0] = 0
    ys, xs = np.mgrid[: g.shape[0], : g.shape[1]]
    return np.array([(g * xs).sum(), (g * ys).sum()]) / g.sum()


def test_none_is_identity():
    img = textured()
    out = apply_effects(img, CameraEffects.none(), np.random.default_rng(1))
    assert out.dtype == np.uint8 and out.shape == img.shape
    np.testing.assert_array_equal(out, img)
    assert out is not img


def test_deterministic_for_a_seed_and_output_type():
    img = textured()
    fx = CameraEffects(blur_prob=0.5, motion_blur_prob=0.5, jpeg_quality=(60, 90))
    for seed in range(6):
        a = apply_effects(img, fx, np.random.default_rng(seed))
        b = apply_effects(img, fx, np.random.default_rng(seed))
        assert a.dtype == np.uint8 and a.shape == img.shape
        np.testing.assert_array_equal(a, b)
    c = apply_effects(img, fx, np.random.default_rng(100))
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("lo,hi", [(1.0, 1.0), (3.0, 3.0), (0.5, 4.0)])
def test_read_noise_std_within_range(lo, hi):
    flat = np.full((128, 128, 3), 128, np.uint8)
    fx = CameraEffects(noise_std=(lo, hi), shot_noise=(0.0, 0.0), blur_prob=0.0, motion_blur_prob=0.0,
                       vignetting=(0.0, 0.0), gamma_jitter=(1.0, 1.0))
    for seed in range(5):
        out = apply_effects(flat, fx, np.random.default_rng(seed)).astype(np.float64)
        assert abs(out.mean() - 128) < 0.1
        # Rounding to integers adds variance 1/12.
        std = np.sqrt(max(out.var() - 1 / 12, 0.0))
        assert lo * 0.95 <= std <= hi * 1.05, (seed, std)


def test_shot_noise_grows_with_intensity():
    fx = CameraEffects(noise_std=(0.0, 0.0), shot_noise=(0.5, 0.5), blur_prob=0.0, motion_blur_prob=0.0,
                       vignetting=(0.0, 0.0), gamma_jitter=(1.0, 1.0))
    for level in (16, 64, 196):
        out = apply_effects(np.full((128, 128, 3), level, np.uint8), fx, np.random.default_rng(level))
        std = out.astype(np.float64).std()
        assert abs(std - 0.5 * np.sqrt(level)) < 0.1 * 0.5 * np.sqrt(level) + 0.1, (level, std)


def test_default_noise_within_combined_range():
    flat = np.full((96, 96, 3), 128, np.uint8)
    fx = CameraEffects(blur_prob=0.0, motion_blur_prob=0.0, vignetting=(0.0, 0.0), gamma_jitter=(1.0, 1.0))
    max_std = np.sqrt(4.0 ** 2 + 0.6 ** 2 * 128)
    for seed in range(10):
        std = apply_effects(flat, fx, np.random.default_rng(seed)).astype(np.float64).std()
        assert std <= max_std * 1.05 + 0.3


@pytest.mark.parametrize("pp", [None, (70.0, 40.0)])
def test_vignetting_darkens_corners_not_centre(pp):
    h, w = 120, 160
    flat = np.full((h, w, 3), 200, np.uint8)
    fx = CameraEffects(noise_std=(0, 0), shot_noise=(0, 0), blur_prob=0, motion_blur_prob=0,
                       vignetting=(0.4, 0.4), gamma_jitter=(1, 1))
    out = apply_effects(flat, fx, np.random.default_rng(0), principal_point=pp).astype(int)
    cx, cy = pp if pp is not None else ((w - 1) / 2, (h - 1) / 2)
    centre = out[int(round(cy)), int(round(cx))]
    assert np.all(np.abs(centre - 200) <= 2)
    corners = [out[0, 0], out[0, -1], out[-1, 0], out[-1, -1]]
    for c in corners:
        assert np.all(c < centre - 10)
    # The farthest corner falls by the full strength.
    assert abs(min(c.mean() for c in corners) - 200 * 0.6) <= 2
    # Falloff is monotonic along a row through the principal point.
    row = out[int(round(cy)), int(round(cx)):, 0]
    assert np.all(np.diff(row) <= 0)
    g = vignetting_gain(w, h, 0.4, pp)
    assert g.shape == (h, w) and g.max() <= 1.0


@pytest.mark.parametrize("kind", ["defocus", "motion"])
def test_blur_keeps_a_dot_in_place(kind):
    for seed in range(8):
        img = np.full((64, 80, 3), 20, np.uint8)
        rng = np.random.default_rng(seed)
        x, y = int(rng.integers(20, 60)), int(rng.integers(20, 44))
        img[y - 1:y + 2, x - 1:x + 2] = 250
        if kind == "defocus":
            fx = CameraEffects(noise_std=(0, 0), shot_noise=(0, 0), blur_prob=1.0, blur_sigma=(1.5, 1.5),
                               motion_blur_prob=0.0, vignetting=(0, 0), gamma_jitter=(1, 1))
        else:
            fx = CameraEffects(noise_std=(0, 0), shot_noise=(0, 0), blur_prob=0.0, motion_blur_prob=1.0,
                               motion_blur_px=(9.0, 9.0), vignetting=(0, 0), gamma_jitter=(1, 1))
        out = apply_effects(img, fx, rng)
        assert not np.array_equal(out, img)
        assert np.linalg.norm(centroid(out) - [x, y]) < 0.25, (seed, centroid(out), (x, y))


def test_motion_kernel_is_centred_and_normalised():
    for length, angle in [(2.0, 0.0), (5.5, 0.7), (9.0, 2.0)]:
        k = motion_blur_kernel(length, angle)
        assert k.shape[0] == k.shape[1] and k.shape[0] % 2 == 1
        assert abs(k.sum() - 1) < 1e-12
        r = k.shape[0] // 2
        ys, xs = np.mgrid[-r:r + 1, -r:r + 1]
        assert abs((k * xs).sum()) < 1e-12 and abs((k * ys).sum()) < 1e-12
        # Extent along the blur direction matches the length (second moment of a uniform segment).
        along = xs * np.cos(angle) + ys * np.sin(angle)
        assert abs(np.sqrt((k * along ** 2).sum()) - length / np.sqrt(12)) < 0.35


def test_jpeg_changes_appearance_only_slightly():
    img = np.full((64, 64, 3), 120, np.uint8)
    img[20:40, 20:40] = (200, 80, 60)
    fx = CameraEffects(noise_std=(0, 0), shot_noise=(0, 0), blur_prob=0, motion_blur_prob=0,
                       vignetting=(0, 0), gamma_jitter=(1, 1), jpeg_quality=(40, 40))
    out = apply_effects(img, fx, np.random.default_rng(0))
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert np.abs(out.astype(int) - img).mean() < 6


def test_gamma_keeps_extremes():
    img = np.zeros((8, 8, 3), np.uint8)
    img[:, 4:] = 255
    img[0, 0] = 128
    fx = CameraEffects(noise_std=(0, 0), shot_noise=(0, 0), blur_prob=0, motion_blur_prob=0,
                       vignetting=(0, 0), gamma_jitter=(1.2, 1.2))
    out = apply_effects(img, fx, np.random.default_rng(0))
    assert out[1, 0, 0] == 0 and out[1, 7, 0] == 255 and out[0, 0, 0] < 128


def test_from_dict():
    fx = CameraEffects.from_dict({"noise_std": [1, 2], "blur_prob": 0.5, "jpeg_quality": [70, 95]})
    assert fx.noise_std == (1.0, 2.0) and fx.blur_prob == 0.5 and fx.jpeg_quality == (70, 95)
    assert fx.vignetting == CameraEffects().vignetting
    with pytest.raises(ValueError, match="noise_sigma"):
        CameraEffects.from_dict({"noise_sigma": [1, 2], "blur_prob": 0.1})
    with pytest.raises(ValueError, match="blur_prob"):
        CameraEffects(blur_prob=1.5)
    with pytest.raises(ValueError, match="noise_std"):
        CameraEffects(noise_std=(3.0, 1.0))


def test_rejects_non_uint8_rgb():
    with pytest.raises(ValueError):
        apply_effects(np.zeros((8, 8, 3), np.float32), CameraEffects(), np.random.default_rng(0))
    with pytest.raises(ValueError):
        apply_effects(np.zeros((8, 8), np.uint8), CameraEffects(), np.random.default_rng(0))
