"""The domains the free-space tests share: the rooms joined by their door, a wall that
splits the square into two components, and a disc with a rectangle."""

from harness.domains.obstacles import Obstacles
from harness.domains.rooms import Rooms

WALL = [[0.47, 0.0], [0.53, 0.0], [0.53, 1.0], [0.47, 1.0]]
"""A wall across the whole square at x = 0.5 (length): two components of free space."""

DOMAINS = {
    "rooms": Rooms(),
    "shut_rooms": Obstacles(polygons=[WALL]),
    "obstacles": Obstacles(
        discs=[{"center": [0.5, 0.5], "radius": 0.15}],
        polygons=[[[0.1, 0.7], [0.3, 0.7], [0.3, 0.8], [0.1, 0.8]]],
    ),
}
"""Name -> domain, in the order the tests are parametrised."""
