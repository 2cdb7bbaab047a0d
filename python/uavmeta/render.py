"""Pictures of the world as RGB arrays (H, W, 3) of uint8, drawn with numpy alone.

North is up: cell (x, y) is drawn in column x, row L-1-y. Rain cells are blue, each device a
square coloured from green (fresh, A = 1) to red (A = aoi_max, on a log scale), the UAV a dark
disc, and a trajectory an orange line through the cell centres it visited. Save a frame with any
image library, e.g. ``PIL.Image.fromarray(env.render()).save("world.png")``.
"""

import math

import numpy as np

BACKGROUND = (255, 255, 255)
GRID = (205, 205, 205)
RAIN = (150, 190, 240)
PATH = (240, 140, 20)
UAV = (30, 30, 60)


def cell_pixels(grid_cells):
    """Pixels per cell side: 32 on the default 10 x 10 grid, fewer on large grids."""
    return max(2, min(32, 640 // grid_cells))


def frame(worlds, i=0, trajectory=None, trajectories=()):
    """Env ``i`` of the native ``worlds`` as an RGB array, every UAV a disc, with
    ``trajectory`` (a list of (x, y) cells) or ``trajectories`` (one such list a UAV) drawn
    under them."""
    _uav, _t, rain, aoi = worlds.state(i)
    n, px = worlds.grid_cells, cell_pixels(worlds.grid_cells)
    img = np.empty((n * px + 1, n * px + 1, 3), dtype=np.uint8)
    img[:] = BACKGROUND
    if rain is not None:
        x0, y0, x1, y1 = rain
        rows, cols = _cells(n, px, x0, y0, x1, y1)
        img[rows, cols] = RAIN
    img[::px, :] = GRID
    img[:, ::px] = GRID
    for k, (dx, dy) in enumerate(worlds.device_cells(i)):
        inset = max(1, px // 4)
        rows, cols = _cells(n, px, dx, dy, dx, dy)
        img[rows.start + inset : rows.stop - inset, cols.start + inset : cols.stop - inset] = (
            _aoi_colour(aoi[k], worlds.aoi_max)
        )
    for path in [trajectory, *trajectories]:
        if path:
            _draw_path(img, n, px, path)
    for ux, uy in worlds.uav_cells(i):
        _draw_disc(img, _centre(n, px, ux, uy), max(1.0, px * 0.3), UAV)
    return img


def _cells(n, px, x0, y0, x1, y1):
    """Row and column slices of the rectangle of cells (x0, y0)..(x1, y1), inclusive."""
    return slice((n - 1 - y1) * px, (n - y0) * px + 1), slice(x0 * px, (x1 + 1) * px + 1)


def _centre(n, px, x, y):
    """(row, column) of the centre of cell (x, y)."""
    return (n - 1 - y) * px + px // 2, x * px + px // 2


def _aoi_colour(a, aoi_max):
    t = math.log(a) / math.log(aoi_max) if aoi_max > 1 else 0.0
    t = min(1.0, max(0.0, t))
    return (int(40 + 200 * t), int(180 - 140 * t), 60)


def _draw_path(img, n, px, cells):
    half = max(1, px // 16)
    r, c = _centre(n, px, *cells[0])  # the start: a square
    img[r - 3 * half : r + 3 * half + 1, c - 3 * half : c + 3 * half + 1] = PATH
    for (xa, ya), (xb, yb) in zip(cells, cells[1:]):
        (ra, ca), (rb, cb) = _centre(n, px, xa, ya), _centre(n, px, xb, yb)
        r0, r1 = sorted((ra, rb))
        c0, c1 = sorted((ca, cb))
        img[r0 - half : r1 + half + 1, c0 - half : c1 + half + 1] = PATH


def _draw_disc(img, centre, radius, colour):
    r, c = centre
    rows, cols = np.ogrid[: img.shape[0], : img.shape[1]]
    img[(rows - r) ** 2 + (cols - c) ** 2 <= radius * radius] = colour


def trajectory(env, cells=None):
    """An RGB array of the path ``cells`` (default: the env's episode so far) over the world of
    ``env`` (a ``UavEnv``)."""
    return env.unwrapped.render_trajectory(cells)
