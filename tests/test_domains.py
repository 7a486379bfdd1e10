"""Free space resolved on the grid and the robots' raster (harness/domains), against
areas known in closed form, brute-force flood fills and images drawn here.
"""

import os
from collections import deque

import numpy as np
import pytest
from PIL import Image

from harness.domains.base import components
from harness.domains.mask import Mask
from harness.domains.obstacles import Obstacles
from harness.domains.rooms import Rooms
from harness.domains.square import Square
from harness.grid import Grid
from harness.parameters import ParameterError


def flood_labels(cells, face_x, face_y):
    """Component labels by breadth-first search, numbered by first cell in C order."""
    ny, nx = cells.shape
    labels = -np.ones((ny, nx), dtype=int)
    count = 0
    for j in range(ny):
        for i in range(nx):
            if not cells[j, i] or labels[j, i] >= 0:
                continue
            labels[j, i] = count
            queue = deque([(j, i)])
            while queue:
                b, a = queue.popleft()
                steps = []
                if a + 1 < nx and face_x[b, a]:
                    steps.append((b, a + 1))
                if a > 0 and face_x[b, a - 1]:
                    steps.append((b, a - 1))
                if b + 1 < ny and face_y[b, a]:
                    steps.append((b + 1, a))
                if b > 0 and face_y[b - 1, a]:
                    steps.append((b - 1, a))
                for s in steps:
                    if labels[s] < 0:
                        labels[s] = count
                        queue.append(s)
            count += 1
    return labels


def test_the_square_is_free_everywhere():
    grid = Grid.square(12)
    free = Square().resolve(grid)
    assert free.everywhere and free.n_components == 1
    assert free.free_area == pytest.approx(1.0)
    assert not Square(resolution=64).raster(1.0).any()


@pytest.mark.parametrize("n", [30, 64])
def test_a_disc_removes_its_area_to_within_its_boundary_cells(n):
    r = 0.2
    grid = Grid.square(n)
    free = Obstacles(discs=[{"center": [0.5, 0.5], "radius": r}]).resolve(grid)
    exact = 1.0 - np.pi * r**2
    boundary = 2 * np.pi * r * grid.dx  # the cells the circle crosses, at most
    assert abs(free.free_area - exact) <= boundary
    assert free.n_components == 1


def test_points_in_discs_and_polygons_are_blocked_exactly():
    dom = Obstacles(
        discs=[{"center": [0.3, 0.3], "radius": 0.1}],
        polygons=[[[0.6, 0.6], [0.9, 0.6], [0.9, 0.9], [0.6, 0.9]]],
    )
    x = np.array([0.3, 0.3 + 0.0999, 0.3 + 0.1001, 0.75, 0.95, 0.5])
    y = np.array([0.3, 0.3, 0.3, 0.75, 0.75, 0.5])
    assert dom.blocked(x, y, 1.0).tolist() == [True, True, False, True, False, False]


def test_the_rooms_are_one_component_through_their_door():
    assert Rooms().resolve(Grid.square(30)).n_components == 1


def test_a_door_narrower_than_a_cell_is_refused_naming_door():
    with pytest.raises(ParameterError) as err:
        Rooms(door=(0.5, 0.5 + 1e-3)).resolve(Grid.square(30))
    assert err.value.name == "door" and "one cell" in err.value.allowed


def test_no_open_face_crosses_a_wall_thinner_than_a_cell():
    grid = Grid.square(20)  # cells of 0.05; a wall of 0.015 inside one column of cells
    wall = [[0.505, 0.0], [0.52, 0.0], [0.52, 1.0], [0.505, 1.0]]  # left of the centre 0.525
    free = Obstacles(polygons=[wall]).resolve(grid)
    assert free.cells.all()  # the wall covers less than half of any cell
    assert free.n_components == 2  # but closes every face it crosses: no leak


@pytest.mark.parametrize("seed", range(5))
def test_components_match_a_flood_fill(seed):
    rng = np.random.default_rng(seed)
    cells = rng.random((9, 11)) < 0.6
    face_x = cells[:, :-1] & cells[:, 1:] & (rng.random((9, 10)) < 0.8)
    face_y = cells[:-1, :] & cells[1:, :] & (rng.random((8, 11)) < 0.8)
    assert (components(cells, face_x, face_y) == flood_labels(cells, face_x, face_y)).all()


def test_restrict_puts_unit_mass_on_free_cells_only():
    grid = Grid.square(30)
    free = Rooms().resolve(grid)
    p = free.restrict(np.ones(grid.shape))
    assert grid.integrate(p) == pytest.approx(1.0, abs=1e-14)
    assert (p[~free.cells] == 0).all() and (p[free.cells] > 0).all()
    with pytest.raises(ValueError, match="no mass"):
        free.restrict(np.where(free.cells, 0.0, 1.0))


def test_the_raster_agrees_with_the_geometry_at_square_centres():
    dom = Rooms(resolution=64)
    raster = dom.raster(2.0)
    centres = (np.arange(64) + 0.5) * (2.0 / 64)
    x, y = np.meshgrid(centres, centres, indexing="xy")
    assert (raster.astype(bool) == dom.blocked(x, y, 2.0)).all()
    assert raster[:, 32].any() and not raster[:, 0].any()


def _png(path, pixels):
    Image.fromarray(np.asarray(pixels, dtype=np.uint8), mode="L").save(path)
    return str(path)


def test_a_mask_s_top_row_is_the_top_of_the_square(tmp_path):
    image = np.full((8, 8), 255)
    image[:4] = 0  # the top half dark
    dom = Mask(path=_png(tmp_path / "m.png", image))
    assert dom.blocked(np.array([0.5, 0.5]), np.array([0.9, 0.1]), 1.0).tolist() == [True, False]
    free = dom.resolve(Grid.square(16))
    assert free.cells[:8].all() and not free.cells[8:].any()  # grid row 0 at the bottom


def test_the_shipped_mask_loads_and_its_aisles_connect():
    free = Mask().resolve(Grid.square(64))
    assert 0.6 < free.free_area < 0.95 and free.n_components == 1


def _bomb_png(path):
    """A small PNG whose IHDR declares 2^31 - 1 x 2^31 - 1 pixels (Pillow's own limit,
    checked before the mask's, calls it a decompression bomb)."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body)
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", 2**31 - 1, 2**31 - 1, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * 64)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize(
    "kind", ["missing", "text", "fifo", "jpeg", "huge", "directory", "bomb", "critical", "wide"]
)
def test_a_mask_that_is_not_a_readable_png_is_refused_naming_path(tmp_path, kind):
    path = tmp_path / "mask.png"
    if kind == "text":
        path.write_text("not an image")
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "jpeg":
        Image.fromarray(np.zeros((8, 8), dtype=np.uint8), mode="L").save(path, format="JPEG")
    elif kind == "huge":
        Image.new("1", (5000, 5000)).save(path)  # small file, 25 M pixels
    elif kind == "directory":
        path.mkdir()
    elif kind == "bomb":
        _bomb_png(path)
    elif kind == "critical":  # a chunk libpng refuses (Pillow reads past it)
        import struct
        import zlib

        Image.fromarray(np.zeros((8, 8), dtype=np.uint8), mode="L").save(path)
        data = path.read_bytes()
        body = b"x"
        chunk = (
            struct.pack(">I", 1) + b"ABCD" + body + struct.pack(">I", zlib.crc32(b"ABCD" + body))
        )
        path.write_bytes(data[:33] + chunk + data[33:])
    elif kind == "wide":  # within the pixel budget, a side over 4096
        Image.new("L", (5000, 10), 255).save(path)
    with pytest.raises(ParameterError) as err:
        Mask(path=str(path))
    assert err.value.name == "path" and "\n" not in str(err.value)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"discs": [{"center": [0.5, 0.5], "radius": -0.1}]}, "discs[0].radius"),
        ({"discs": [{"center": [0.5], "radius": 0.1}]}, "discs[0].center"),
        ({"discs": [{"radius": 0.1}]}, "discs[0]"),
        ({"polygons": [[[0, 0], [1, 1]]]}, "polygons[0]"),
        ({"polygons": [[[0, 0], [1, "a"], [0, 1]]]}, "polygons[0][1]"),
        ({"resolution": 8}, "resolution"),
        ({"resolution": 100000}, "resolution"),  # 10^10 squares: refused, never allocated
        ({"polygons": [[[0.2, 0.2], [0.6, 0.6], [0.6, 0.2], [0.2, 0.6]]]}, "polygons[0]"),
        ({"polygons": [[[0.2, 0.2], [0.4, 0.4], [0.6, 0.6]]]}, "polygons[0]"),  # no area
        ({"polygons": [[[0.2, 0.2], [0.2, 0.2], [0.2, 0.2]]]}, "polygons[0]"),  # one point
        ({"discs": [{"center": [0.5, 0.5], "radius": 0.1, "color": "red"}]}, "discs[0]"),
    ],
    ids=["negative-radius", "one-coordinate", "no-center", "two-vertices", "text-vertex",
         "resolution-8", "resolution-huge", "bow-tie", "collinear", "one-point", "unknown-key"],
)  # fmt: skip
def test_bad_obstacles_are_refused_naming_the_parameter(kwargs, name):
    with pytest.raises(ParameterError) as err:
        Obstacles(**kwargs)
    assert err.value.name == name


def test_obstacles_covering_the_square_are_refused():
    dom = Obstacles(discs=[{"center": [0.5, 0.5], "radius": 2.0}])
    with pytest.raises(ParameterError, match="free space"):
        dom.resolve(Grid.square(10))


def test_the_gradient_on_the_square_s_free_space_is_the_grid_s(rng):
    grid = Grid.square(14)
    f = rng.random(grid.shape)
    assert np.array_equal(Square().resolve(grid).gradient(f), grid.gradient(f))


def test_the_gradient_reflects_at_closed_faces_as_at_walls():
    """A field that depends on x only, linear in each room: the gradient is exact inside
    each room, and a cell next to the wall uses itself as its ghost neighbour."""
    grid = Grid.square(20)
    wall = [[0.47, 0.0], [0.53, 0.0], [0.53, 1.0], [0.47, 1.0]]
    free = Obstacles(polygons=[wall]).resolve(grid)
    f = grid.mesh[0].copy()
    g = free.gradient(f)
    left_edge = np.flatnonzero(free.cells[5])  # a row away from the door
    cols = left_edge[(left_edge > 0) & (left_edge < 19)]
    inside = [c for c in cols if free.face_x[5, c - 1] and free.face_x[5, c]]
    np.testing.assert_allclose(g[0, 5, inside], 1.0)
    beside = [c for c in cols if free.face_x[5, c - 1] != free.face_x[5, c]]
    assert beside and np.allclose(g[0, 5, beside], 0.5)  # half, as at the rectangle's walls
    assert (g[:, ~free.cells] == 0).all()


def test_a_part_that_does_not_honour_obstacles_is_refused_on_them(refusal):
    line = refusal(["domain=rooms", "init=left_room", "grid.n=12", "agents.n=40",
                    "estimator=injected"])  # fmt: skip
    assert line is not None and line.startswith("invalid config: domain='rooms': square"), line
    assert "estimator=injected" in line
    assert "runs on" in line


def test_obstacles_that_cover_every_cell_are_refused_naming_domain(refusal):
    line = refusal(["domain=obstacles", "grid.n=12", "~domain.polygons",
                    "domain.discs=[{center:[0.5,0.5],radius:2.0}]"])  # fmt: skip
    assert line is not None and line.startswith("invalid config: domain='obstacles': "), line
    assert "free space" in line


def test_a_target_in_a_component_no_robot_starts_in_is_refused(refusal):
    wall = "[[[0.47,0.0],[0.53,0.0],[0.53,1.0],[0.47,1.0]]]"
    line = refusal(["domain=obstacles", "grid.n=12", "~domain.discs",
                    f"domain.polygons={wall}", "init=left_room"])  # fmt: skip
    assert line is not None and line.startswith("invalid config: target='three_bumps': "), line
    assert "no robot starts" in line


def test_a_door_narrower_than_a_cell_is_refused_on_the_command_line(refusal):
    line = refusal(["domain=rooms", "grid.n=12", "domain.door=[0.5,0.55]"])
    assert line is not None and line.startswith("invalid config: domain.door="), line


def test_an_initial_density_inside_a_wall_is_refused_in_one_line(refusal):
    """The box lies in the wall between the rooms, on cells whose centres are free: the
    robots' map of obstacles decides, before anything runs."""
    line = refusal(["domain=rooms", "grid.n=12", "agents.n=40", "init=paper_box",
                    "init.x0=0.47", "init.x1=0.53", "init.y0=0.1", "init.y1=0.3"])  # fmt: skip
    assert line is not None and line.startswith("invalid config: init='paper_box': "), line
    assert "(it puts 0 there)" in line


def test_a_target_with_only_round_off_in_free_space_is_refused(refusal):
    """A bump inside a disc has a tail of ~1e-49 outside it and a floor of 1e-9:
    renormalised, it would be another target."""
    line = refusal(["domain=obstacles", "grid.n=12", "agents.n=40", "~domain.polygons",
                    "domain.discs=[{center:[0.5,0.5],radius:0.3}]", "target.means=[[0.5,0.5]]",
                    "target.weights=[1.0]", "target.stds=[0.02]", "target.floor=1e-9"])  # fmt: skip
    assert line is not None and line.startswith("invalid config: target='three_bumps': "), line
    assert "at least 0.001 of its mass in free space" in line


def test_a_16_bit_mask_reads_its_grey_levels_scaled_not_clipped(tmp_path):
    """A 30 % grey wall in a 16-bit image is a wall at threshold 0.5, as in 8 bits."""
    image = np.full((16, 16), 65535, dtype=np.uint16)
    image[:, 7:9] = int(0.3 * 65535)
    path = tmp_path / "wall16.png"
    Image.fromarray(image).save(path)  # a 16-bit grey PNG (mode I;16)
    dom = Mask(path=str(path))
    assert dom.blocked(np.array([0.5, 0.1]), np.array([0.5, 0.5]), 1.0).tolist() == [True, False]


def test_a_transparent_background_is_free_and_an_opaque_obstacle_blocked(tmp_path):
    rgba = np.zeros((16, 16, 4), dtype=np.uint8)  # transparent black everywhere
    rgba[6:10, 6:10] = (0, 0, 0, 255)  # an opaque black square in the middle
    path = tmp_path / "drawn.png"
    Image.fromarray(rgba, mode="RGBA").save(path)
    dom = Mask(path=str(path))
    assert dom.blocked(np.array([0.5, 0.1]), np.array([0.5, 0.1]), 1.0).tolist() == [True, False]


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"discs": [{"center": [5.0, 5.0], "radius": 0.1}]}, "discs[0]"),
        ({"polygons": [[[-2, -2], [3, -2], [3, -1]]]}, "polygons[0]"),
        ({"polygons": [[[0.2, 0.2], [0.4, 0.2], [0.3, 0.4]], [[1, 1], [2, 1], [2, 2]]]},
         "polygons[1]"),
    ],
    ids=["disc-far-away", "polygon-below", "second-polygon-touching-a-corner"],
)  # fmt: skip
def test_an_obstacle_outside_the_square_is_refused_naming_it(kwargs, name):
    """A shape that covers no part of the square (touching a corner covers no area)."""
    dom = Obstacles(**kwargs)
    with pytest.raises(ParameterError) as err:
        dom.resolve(Grid.square(12))
    assert err.value.name == name and "outside" in str(err.value)


def test_a_16_bit_mask_s_transparent_level_is_free(tmp_path):
    """A 16-bit grey mask whose tRNS marks its background level transparent: the
    background is free as in 8 bits, the dark patch is blocked."""
    image = np.full((16, 16), 1000, dtype=np.uint16)  # dark, but transparent
    image[6:10, 6:10] = 500  # dark and opaque
    path = tmp_path / "patch16.png"
    Image.fromarray(image).save(path, transparency=1000)
    dom = Mask(path=str(path))
    assert dom.blocked(np.array([0.5, 0.1]), np.array([0.5, 0.1]), 1.0).tolist() == [True, False]


def test_a_disc_touching_the_square_from_outside_is_refused():
    """Touching is no area: as for polygons."""
    dom = Obstacles(discs=[{"center": [-0.1, 0.5], "radius": 0.1}], polygons=[])
    with pytest.raises(ParameterError) as err:
        dom.resolve(Grid.square(12))
    assert err.value.name == "discs[0]" and "outside" in str(err.value)
