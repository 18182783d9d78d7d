"""Reading the markdown tables the benchmarks render."""


def row_cells(lines, first):
    """The cells of the table row whose first cell is ``first``."""
    for line in lines:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0] == first:
            return cells
    raise AssertionError(f"no row {first!r} in {lines}")
