"""PointRaster: many points drawn as one image, where a scatter would put them."""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from forestreg.engine.report.raster import add_points  # noqa: E402


def _render(fig, dpi):
    fig.set_dpi(dpi)
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba()).copy()


@pytest.mark.parametrize("dpi", [72, 100, 137])
def test_points_land_on_the_pixels_of_their_data_coordinates(dpi):
    fig, ax = plt.subplots(figsize=(4, 3))
    pts = np.array([[1.0, 1.0], [9.0, 4.0], [5.0, 2.5], [2.2, 3.9], [20.0, 20.0], [-3.0, 1.0]])  # two outside the axes
    add_points(ax, [(pts, "red", 0.01)])
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 5)
    img = _render(fig, dpi)
    red = {tuple(p) for p in np.argwhere((img[:, :, 0] == 255) & (img[:, :, 1] == 0) & (img[:, :, 2] == 0)).tolist()}
    disp = ax.transData.transform(pts[:4])  # display pixels, origin at the bottom left
    want = {(int(img.shape[0] - 1 - np.floor(y)), int(np.floor(x))) for x, y in disp}
    assert red == want  # one pixel each (the marker is smaller than a pixel), the outside ones clipped
    plt.close(fig)


def test_marker_size_later_layers_on_top_and_data_limits():
    fig, ax = plt.subplots(figsize=(4, 4))
    rgba = np.array([[0, 0, 255, 255], [0, 255, 0, 255]], dtype=np.uint8)  # bytes per point, used as given
    add_points(
        ax, [(np.array([[0.0, 0.0], [4.0, 4.0]]), "red", 30.0), (np.array([[0.0, 0.0], [10.0, 10.0]]), rgba, 1.0)]
    )
    lo, hi = ax.get_xlim()
    assert lo < 0.0 and hi > 10.0  # the points count in the autoscaled limits, as a scatter's
    img = _render(fig, 100)
    count = {
        name: int(((img[:, :, 0] == r) & (img[:, :, 1] == g) & (img[:, :, 2] == b)).sum())
        for name, (r, g, b) in {"red": (255, 0, 0), "blue": (0, 0, 255), "green": (0, 255, 0)}.items()
    }
    # s = 30 points squared: a disc of sqrt(30) * 100 / 72 = 7.6 px across, a quarter pixel wider
    # for the antialiased edge (radius 4.05 px: ~52 px); the blue point (s = 1: radius 0.94 px,
    # its pixel and up to its four neighbours) covers the red disc's centre
    area = np.pi * (0.5 * np.sqrt(30.0) * 100 / 72 + 0.25) ** 2
    assert 0.85 * 2 * area <= count["red"] + count["blue"] <= 1.15 * 2 * area
    assert 1 <= count["blue"] <= 5 and 1 <= count["green"] <= 5
    x, y = ax.transData.transform([0.0, 0.0])
    assert tuple(img[int(img.shape[0] - 1 - np.floor(y)), int(np.floor(x)), :3]) == (0, 0, 255)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=50)  # another dpi at saving: drawn again at that scale
    assert buf.getvalue()[:4] == b"\x89PNG"
    plt.close(fig)


def test_colour_count_must_match_the_points():
    fig, ax = plt.subplots()
    with pytest.raises(ValueError, match="3 colours for 2 points"):
        add_points(ax, [(np.zeros((2, 2)), ["r", "g", "b"], 1.0)])
    plt.close(fig)


@pytest.mark.parametrize("radius", [0.3, 0.75, 1.08, 2.16, 3.5])
def test_painted_discs_equal_a_pixel_by_pixel_painting(radius):
    """paint_discs (rings pruned to those a disc can reach, outer rings first) paints what a
    point-by-point, pixel-by-pixel painting in the same order of rings paints."""
    from forestreg.engine.report.pixels import paint_discs

    rng = np.random.default_rng(int(radius * 100))
    pixels = rng.uniform(-3, 43, (300, 2))
    colours = rng.integers(0, 255, (300, 3), dtype=np.uint8)
    got = np.zeros((40, 40, 3), dtype=np.uint8)
    paint_discs(got, pixels, colours[0], radius, colours)
    want = np.zeros_like(got)
    reach = int(np.ceil(radius)) + 1  # one ring more than needed: the pruning must not matter
    rings = sorted(
        ((dc, dr) for dr in range(-reach, reach + 1) for dc in range(-reach, reach + 1)),
        key=lambda o: -(o[0] ** 2 + o[1] ** 2),
    )
    for dc, dr in rings:
        for k, (x, y) in enumerate(pixels):
            c, r = int(np.floor(x)) + dc, int(np.floor(y)) + dr
            if not (0 <= c < 40 and 0 <= r < 40):
                continue
            if (dc or dr) and (c + 0.5 - x) ** 2 + (r + 0.5 - y) ** 2 > radius * radius:
                continue
            want[r, c] = colours[k]
    np.testing.assert_array_equal(got, want)
