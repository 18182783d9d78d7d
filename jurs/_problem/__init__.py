"""The fitting problem: offset samples and their layout (eq. 4-5, 9), the energies and
metrics defined on it (eq. 16-19, 31-37), input checks, and the size ladder of compiled
shapes."""
