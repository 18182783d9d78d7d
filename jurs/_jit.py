"""A jit whose per-call work is a flatten and a dictionary look-up (``FlatJit``): for the
compiled programs that a warm top-level fit calls, where equinox's ``filter_jit``
dispatch costs as much as a small fit's compiled work."""

from __future__ import annotations

import equinox as eqx
import jax

from ._kept import KeptByIdentity


class FlatJit:
    """``fn`` jit-compiled over the flat array leaves of its arguments, one program per
    tree structure and static part. What equinox's ``filter_jit`` does, with the per-call
    work cut to a partition, a flatten and a dictionary look-up: at top level that per-call
    work is what a warm fit of a small cloud pays beyond its compiled solve
    (``benchmarks/startup.py``, the overhead case)."""

    def __init__(self, fn):
        self.fn = fn
        self.programs: dict = {}
        # The split of a Module argument seen before (a Cloud's kept Problem): the same
        # immutable Module splits the same way.
        self.splits = KeptByIdentity()

    def _split(self, arg) -> tuple:
        """``(leaves, tree, static)`` of one argument."""
        return self.splits.get(arg, _split) if isinstance(arg, eqx.Module) else _split(arg)

    def __call__(self, *args):
        splits = [self._split(arg) for arg in args]
        leaves = [leaf for split in splits for leaf in split[0]]
        trees = tuple(split[1] for split in splits)
        static = tuple(split[2] for split in splits)
        static_leaves, static_tree = jax.tree_util.tree_flatten(static)
        key = (trees, static_tree, tuple(static_leaves))
        try:
            program = self.programs.get(key)
        except TypeError:  # an unhashable static part: equinox handles it
            return eqx.filter_jit(self.fn)(*args)
        if program is None:
            program = self.programs[key] = self._compile(trees, static)
        out_leaves, (out_tree, others, at) = program(leaves)
        # The output's leaves: its arrays where they were, its other leaves kept as traced.
        full = list(others)
        for position, leaf in zip(at, out_leaves):
            full[position] = leaf
        return jax.tree_util.tree_unflatten(out_tree, full)

    def _compile(self, trees, static):
        # The output's static part is known once traced; kept beside the program.
        kept: list = []
        sizes = [tree.num_leaves for tree in trees]

        def flat(leaves):
            args, start = [], 0
            for tree, size, part in zip(trees, sizes, static):
                dynamic = jax.tree_util.tree_unflatten(tree, leaves[start : start + size])
                args.append(eqx.combine(dynamic, part))
                start += size
            out = self.fn(*args)
            out_all, out_tree = jax.tree_util.tree_flatten(out)
            at = [i for i, leaf in enumerate(out_all) if eqx.is_array(leaf)]
            others = [None if eqx.is_array(leaf) else leaf for leaf in out_all]
            kept[:] = [(out_tree, others, at)]
            return [out_all[i] for i in at]

        # Named as the function it runs: JAX's cache files and compile events say ``_run``.
        flat.__name__ = flat.__qualname__ = getattr(self.fn, "__name__", "flat")
        jitted = jax.jit(flat)
        return lambda leaves: (jitted(leaves), kept[0])


def _split(arg) -> tuple:
    """``(leaves, tree, static)``: ``arg``'s array leaves, their tree and the rest."""
    dynamic, static = eqx.partition(arg, eqx.is_array)
    leaves, tree = jax.tree_util.tree_flatten(dynamic)
    return leaves, tree, static
