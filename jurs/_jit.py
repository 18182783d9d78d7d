"""How jurs's compiled calls take their arguments: a jit whose per-call work is a flatten
and a dictionary look-up (``FlatJit``), for the compiled programs that a warm top-level fit
calls, where equinox's ``filter_jit`` dispatch costs as much as a small fit's compiled
work; and a solver's Python floats as arrays (``as_arrays``), so that a new value
compiles nothing."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._kept import KeptByIdentity
from ._model.precision import scalar_array
from ._problem.validate import is_concrete


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
        key = tuple((split[1], split[2]) for split in splits)
        try:
            program = self.programs.get(key)
        except TypeError:  # an unhashable static leaf: equinox handles it
            return eqx.filter_jit(self.fn)(*args)
        if program is None:
            program = self.programs[key] = self._compile(key)
        out_leaves, (out_tree, others, at) = program(leaves)
        # The output's leaves: its arrays where they were, its other leaves kept as traced.
        full = list(others)
        for position, leaf in zip(at, out_leaves):
            full[position] = leaf
        return jax.tree_util.tree_unflatten(out_tree, full)

    def _compile(self, key):
        # The output's static part is known once traced; kept beside the program.
        kept: list = []
        sizes = [tree.num_leaves - len(static) for tree, static in key]

        def flat(leaves):
            args, start = [], 0
            for (tree, static), size in zip(key, sizes):
                args.append(_joined(tree, static, leaves[start : start + size]))
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
    """``(arrays, tree, static)``: ``arg``'s array leaves, the tree of all its leaves and
    its other leaves with their places: one flatten, where ``eqx.partition`` maps the tree
    and flattens it again."""
    if isinstance(arg, jax.Array | np.ndarray):
        return [arg], _ARRAY_TREE, ()
    everything, tree = jax.tree_util.tree_flatten(arg)
    arrays = [leaf for leaf in everything if eqx.is_array(leaf)]
    static = tuple((i, leaf) for i, leaf in enumerate(everything) if not eqx.is_array(leaf))
    return arrays, tree, static


_ARRAY_TREE = jax.tree_util.tree_structure(0)


def _joined(tree, static: tuple, arrays: list):
    """The argument that ``_split`` split, with ``arrays`` (traced) in its arrays' places."""
    everything: list = [None] * tree.num_leaves
    for i, leaf in static:
        everything[i] = leaf
    places = sorted(set(range(tree.num_leaves)).difference(i for i, _ in static))
    for i, array in zip(places, arrays, strict=True):
        everything[i] = array
    return jax.tree_util.tree_unflatten(tree, everything)


def as_arrays(tree, dtype):
    """Python floats -> 0-d arrays, so new hyperparameter values do not recompile. NumPy's:
    a jit traces them as it traces JAX arrays, and making one dispatches nothing. A Module
    (a solver) converted before, while it lives, is the same converted Module: the
    compiled call then reuses its split (``jurs._jit.FlatJit``)."""
    if not isinstance(tree, eqx.Module) or not is_concrete(tree):
        return _floats_as_arrays(tree, dtype)
    converted = _converted.get(tree, lambda _: {})
    key = jnp.dtype(dtype).name
    if key not in converted:
        converted[key] = _floats_as_arrays(tree, dtype)
    return converted[key]


def _floats_as_arrays(tree, dtype):
    return jax.tree_util.tree_map(
        lambda x: scalar_array(x, dtype) if isinstance(x, float) else x, tree
    )


#: The conversions made by ``as_arrays`` of each Module, by dtype.
_converted = KeptByIdentity()
