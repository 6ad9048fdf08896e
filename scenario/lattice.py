"""Where a hall's gNBs stand: the 6 x 3 gNB lattice of the TR 38.901 InF layouts (Table 7.8-7)
and its subsets, in the hall frame of ``scenario.schema.HallConfig`` (metres, x along the
length). Positions only; the propagation is netsim's (netsim/nr/layout.py)."""

from __future__ import annotations

LATTICE_COLUMNS = 6  # along x (the hall length)
LATTICE_ROWS = 3  # along y (the hall width)

# Which lattice points a subset of n gNBs uses, as (column, row): a block around the hall centre.
# The lattice has an even number of columns and an odd number of rows, so 2, 4, 6 and 18 gNBs
# sit symmetrically about the centre; 1 and 9 sit half a pitch towards x = 0.
LATTICE_SUBSETS: dict[int, tuple[tuple[int, int], ...]] = {
    1: ((2, 1),),
    2: ((2, 1), (3, 1)),
    4: ((1, 1), (2, 1), (3, 1), (4, 1)),
    6: tuple((c, r) for r in range(3) for c in (2, 3)),
    9: tuple((c, r) for r in range(3) for c in (1, 2, 3)),
    18: tuple((c, r) for r in range(LATTICE_ROWS) for c in range(LATTICE_COLUMNS)),
}
GNB_COUNTS: tuple[int, ...] = tuple(sorted(LATTICE_SUBSETS))


def lattice_index(column: int, row: int) -> int:
    """Index of a lattice point: row-major, x fastest (0 .. 17)."""
    return row * LATTICE_COLUMNS + column


def lattice_subset(count: int) -> tuple[int, ...]:
    """Lattice indices of the subset of ``count`` gNBs (1, 2, 4, 6, 9 or 18), ascending."""
    if count not in LATTICE_SUBSETS:
        raise ValueError(f"{count} gNBs is not a lattice subset: allowed "
                         f"{', '.join(map(str, GNB_COUNTS))}")
    return tuple(sorted(lattice_index(c, r) for c, r in LATTICE_SUBSETS[count]))


def lattice_points_m(hall_length_m: float, hall_width_m: float, bs_height_m: float
                     ) -> list[tuple[float, float, float]]:
    """The 18 lattice points (x, y, z), metres, in ``lattice_index`` order.

    Pitch L / 6 along x and W / 3 along y, half a pitch from the walls: in the Table 7.8-7 halls
    this is the square lattice of spacing D (120 / 6 = 60 / 3 = 20 m, 300 / 6 = 150 / 3 = 50 m);
    in another hall the lattice stretches with it.
    """
    px, py = hall_length_m / LATTICE_COLUMNS, hall_width_m / LATTICE_ROWS
    return [((c + 0.5) * px, (r + 0.5) * py, bs_height_m)
            for r in range(LATTICE_ROWS) for c in range(LATTICE_COLUMNS)]
