"""``domain``: the free space the robots and densities live in.

A domain is the rectangle of the grid less its obstacles. Each option of the config
group is one module: :mod:`~harness.domains.square` (no obstacle: the paper's unit
square), :mod:`~harness.domains.obstacles` (discs and polygons listed in length units),
:mod:`~harness.domains.rooms` (two rooms joined by one door) and
:mod:`~harness.domains.mask` (free space read from a PNG). What they share, and how free
space is resolved on the control grid (cells and faces) and on the robots' finer raster,
is :mod:`~harness.domains.base`.
"""
