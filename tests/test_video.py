"""Video clips: frame count, timestamps (constant and variable rate), positions, interrupted writes, errors."""

import numpy as np
import pytest

from surftrack.io.video import VideoWriter, read_video_frames

W, H = 64, 48


def square_frame(i):
    """A bright 6x6 square on a dark background at a position that moves with i; returns the frame and
    the square's centre (pixel-centre coordinates)."""
    img = np.full((H, W, 3), 30, np.uint8)
    x0, y0 = 4 + 2 * i, 6 + i
    img[y0:y0 + 6, x0:x0 + 6] = (230, 220, 210)
    return img, np.array([x0 + 2.5, y0 + 2.5])


def centroid(gray):
    g = gray.astype(np.float64) - 30
    g[g < 40] = 0
    ys, xs = np.mgrid[: g.shape[0], : g.shape[1]]
    return np.array([(g * xs).sum(), (g * ys).sum()]) / g.sum()


def write_clip(path, times, fps=25.0, explicit=True):
    centres = []
    with VideoWriter(path, fps, W, H) as writer:
        for i, t in enumerate(times):
            img, c = square_frame(i)
            writer.write(img, t if explicit else None)
            centres.append(c)
    return centres


@pytest.mark.parametrize("mode", ["constant", "variable"])
def test_roundtrip_times_and_positions(tmp_path, mode):
    n = 20
    if mode == "constant":
        times = [i / 25.0 for i in range(n)]
    else:
        times = list(np.cumsum([0.0, 0.04, 0.06, 0.03, 0.05, 0.011, 0.09, 0.04, 0.033, 0.067,
                                0.02, 0.1, 0.04, 0.04, 0.05, 0.013, 0.07, 0.04, 0.04, 0.2]))
    path = tmp_path / "clip.mp4"
    centres = write_clip(path, times, explicit=(mode == "variable"))
    frames = list(read_video_frames(path))
    assert len(frames) == n
    np.testing.assert_allclose([t for t, _ in frames], times, atol=1e-3)
    for (t, img), c in zip(frames, centres):
        assert img.dtype == np.uint8 and img.shape == (H, W, 3)
        assert np.linalg.norm(centroid(img.mean(axis=2)) - c) < 1.0
    gray = list(read_video_frames(path, as_gray=True))
    assert len(gray) == n and gray[0][1].shape == (H, W) and gray[0][1].dtype == np.uint8
    assert np.linalg.norm(centroid(gray[5][1]) - centres[5]) < 1.0


def test_interrupted_writer_leaves_a_decodable_file(tmp_path):
    path = tmp_path / "partial.mp4"
    times = [0.0, 0.05, 0.1, 0.2, 0.25, 0.3, 0.41]
    with pytest.raises(RuntimeError, match="boom"):
        with VideoWriter(path, 20.0, W, H) as writer:
            for i, t in enumerate(times):
                writer.write(square_frame(i)[0], t)
            raise RuntimeError("boom")
    assert writer.closed
    frames = list(read_video_frames(path))
    assert len(frames) == len(times)
    np.testing.assert_allclose([t for t, _ in frames], times, atol=1e-3)


def test_writer_checks(tmp_path):
    with pytest.raises(ValueError, match="even"):
        VideoWriter(tmp_path / "odd.mp4", 25.0, 63, 48)
    with pytest.raises(ValueError, match="even"):
        VideoWriter(tmp_path / "odd.mp4", 25.0, 64, 47)
    assert not (tmp_path / "odd.mp4").exists()
    with VideoWriter(tmp_path / "w.mp4", 25.0, W, H) as writer:
        writer.write(square_frame(0)[0], 0.1)
        with pytest.raises(ValueError, match="does not increase"):
            writer.write(square_frame(1)[0], 0.1)
        with pytest.raises(ValueError, match=">= 0"):
            writer.write(square_frame(1)[0], -0.5)
        with pytest.raises(ValueError, match="shape"):
            writer.write(np.zeros((H, W + 2, 3), np.uint8))
    assert len(list(read_video_frames(tmp_path / "w.mp4"))) == 1


def test_read_errors_name_the_path(tmp_path):
    missing = tmp_path / "missing.mp4"
    with pytest.raises(ValueError, match="missing.mp4") as e:
        read_video_frames(missing)
    assert "\n" not in str(e.value)
    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ValueError, match="garbage.mp4") as e:
        list(read_video_frames(garbage))
    assert "\n" not in str(e.value)
