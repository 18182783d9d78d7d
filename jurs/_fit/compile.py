"""XLA options that vectorise the per-bucket sums of large problems, and JAX's persistent
compilation cache for new processes."""

from __future__ import annotations

import os

#: XLA options for ``jax.jit(..., compiler_options=jurs.COMPILER_OPTIONS)``.
#:
#: What they do: allow floating-point reassociation, so that LLVM vectorises sums that
#: XLA's CPU backend otherwise runs as scalar accumulator chains: the per-bucket moment
#: sums of the power form (``jurs._model.basis.power_moments``). NaN and Inf, division and
#: library functions keep their IEEE semantics (the ``honor`` options), so the non-finite
#: checks of the solver driver still work. Measured effect in
#: ``benchmarks/results/speed.md`` (1e6 points, 128 x 128).
#:
#: Who uses them: [`jurs.fit`][] compiles with them the solvers that declare
#: ``reassociation_safe`` (IURS, IPIA, NormalIPIA, LeastSquares) on problems in the bucketed
#: power form (the large ones), when no JAX transformation is tracing: XLA takes compiler
#: options only on an outermost jit. For your own jit of a solver's step or of
#: [`jurs.solve`][], pass them to the outermost ``jax.jit``.
#:
#: Why not everywhere: sums round differently. jurs's own solvers move at the level of the
#: last digits, but an optimiser that wanders near its minimum can end elsewhere (optax's
#: Adam through ``OptimistixMinimiser``): ``benchmarks/results/solvers.md`` compiles every
#: solver both ways. The names are those of XLA's debug options; other backends ignore the
#: CPU ones.
COMPILER_OPTIONS = {
    "xla_cpu_enable_fast_math": True,
    "xla_cpu_fast_math_honor_nans": True,
    "xla_cpu_fast_math_honor_infs": True,
    "xla_cpu_fast_math_honor_division": True,
    "xla_cpu_fast_math_honor_functions": True,
}


def default_cache_dir() -> str:
    """The user's cache folder for jurs (XDG convention): ``$XDG_CACHE_HOME/jurs``, or
    ``~/.cache/jurs`` when ``XDG_CACHE_HOME`` is unset or not absolute."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jurs")


def enable_compilation_cache(path=None, *, min_compile_time_s: float = 0.0) -> str:
    """Turn on JAX's persistent compilation cache, so that new processes load the compiled
    fits of earlier ones instead of compiling them again (a first ``jurs.fit`` compiles for
    seconds; loading takes a fraction of that; ``benchmarks/results/startup.md``).

    jurs never changes JAX's configuration on its own: library users call this (once,
    before their first fit); the ``jurs`` command line calls it unless
    ``--no-compilation-cache`` is given or ``JURS_NO_COMPILATION_CACHE=1`` is set.

    Args:
        path: the cache folder (created if missing). None: the folder JAX already uses
            if one is configured (``JAX_COMPILATION_CACHE_DIR``), else
            ``default_cache_dir`` (``$XDG_CACHE_HOME/jurs`` or ``~/.cache/jurs``).
        min_compile_time_s: store only compilations that took at least this long. JAX's
            own default (1 s) would skip most of a fit's kernels, which each compile in
            well under a second but add up; 0 stores all.

    Returns:
        The folder in use. JAX opens its cache once, at the first compilation that reads
        it: a folder set after that is not switched to (JAX keeps the first).

    JAX's cache skips XLA's compilation but not the tracing before it (a good part of a
    short run: docs/startup.md, "The persistent compilation cache"); so top-level
    [`jurs.fit`][] calls are also kept traced (``jax.export``) in the subfolder
    ``jurs-exported-fits``, keyed by jurs's source, the JAX version and the fit's shapes
    and settings, for a new process to load.

    The cache is trusted code (JAX's entries and the exported fits alike): keep it in a
    folder only you can write to.
    """
    import jax

    if path is None:
        # Config options are attributes made at run time, unknown to a type checker.
        path = jax.config.jax_compilation_cache_dir or default_cache_dir()  # pyright: ignore[reportAttributeAccessIssue]
    path = os.path.abspath(os.path.expanduser(os.fspath(path)))
    exports = os.path.join(path, "jurs-exported-fits")
    os.makedirs(exports, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    global _export_dir
    _export_dir = exports
    return path


# --- Traced fits kept across processes -------------------------------------------------
#
# JAX's persistent cache skips XLA's compilation, not the tracing and lowering before it,
# which are a good part of a command-line run (docs/startup.md, "The persistent
# compilation cache").
# ``enable_compilation_cache`` therefore also keeps each top-level fit exported
# (``jax.export``: traced and lowered to StableHLO) in a folder beside JAX's cache; a new
# process that meets the same shapes and settings loads it and lets JAX's cache supply
# the executable, tracing nothing.

#: Folder of the exported fits, or None (the default): fits are traced as usual.
_export_dir: str | None = None
#: Exports loaded or made in this process, by key (None: exporting failed; not retried).
_exports: dict = {}
_source_digest: str | None = None


def _jurs_source_digest() -> str:
    """A digest of jurs's own source, so that an edited jurs never runs a stale export."""
    global _source_digest
    if _source_digest is None:
        import hashlib

        digest = hashlib.sha256()
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # jurs/
        for folder, subfolders, files in os.walk(root):
            subfolders.sort()
            for name in sorted(f for f in files if f.endswith(".py")):
                with open(os.path.join(folder, name), "rb") as fh:
                    digest.update(name.encode() + b"\0" + fh.read())
        _source_digest = digest.hexdigest()
    return _source_digest


def _export_key(fn, args) -> str:
    """What the traced function depends on: jurs's source, the JAX version and
    configuration, the function, the arguments' tree (static fields included) and the
    shape, dtype and weak type of every array."""
    import hashlib

    import equinox as eqx
    import jax

    leaves, treedef = jax.tree.flatten(args)
    described = [
        (tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False)))
        if eqx.is_array(x)
        else (type(x).__qualname__, repr(x))
        for x in leaves
    ]
    text = repr(
        (
            _jurs_source_digest(),
            jax.__version__,
            jax.default_backend(),
            bool(jax.config.jax_enable_x64),  # pyright: ignore[reportAttributeAccessIssue]
            fn.__module__,
            fn.__qualname__,
            str(treedef),
            described,
        )
    )
    return hashlib.sha256(text.encode()).hexdigest()


def _export(fn, args, dynamic_tree, static):
    """``fn`` exported as a function of the arrays of ``args``, and a skeleton of its
    output (arrays replaced by placeholders) to rebuild the output from the flat results."""
    import equinox as eqx
    import jax
    import numpy as np

    skeleton = []

    def flat(*arrays):
        out = fn(*eqx.combine(jax.tree.unflatten(dynamic_tree, arrays), static))
        skeleton.append(
            jax.tree.map(lambda x: np.zeros((), np.int8) if eqx.is_array(x) else x, out)
        )
        return [x for x in jax.tree.leaves(out) if eqx.is_array(x)]

    exported = jax.export.export(jax.jit(flat))(*jax.tree.leaves(eqx.filter(args, eqx.is_array)))
    return exported, skeleton[0]


def _load_or_export(fn, args, key: str, dynamic_tree, static):
    """The export of ``key``: from this process, from the folder, or made and written."""
    import dataclasses
    import pickle

    if key in _exports:
        return _exports[key]
    assert _export_dir is not None  # only called once the cache is enabled
    path = os.path.join(_export_dir, key + ".pickle")
    entry = None
    try:
        with open(path, "rb") as fh:
            entry = pickle.load(fh)  # trusted, as JAX's own cache is
    except Exception:  # missing, or unreadable (another version): export again
        entry = None
    if entry is None:
        try:
            entry = _export(fn, args, dynamic_tree, static)
        except Exception:  # not exportable (a host callback, a custom call): trace as usual
            _exports[key] = None
            return None
        try:  # written whole, then renamed: a reader never sees half a file
            tmp = f"{path}.{os.getpid()}.tmp"
            with open(tmp, "wb") as fh:  # the VJP rule is a closure and is not needed
                pickle.dump((dataclasses.replace(entry[0], _get_vjp=None), entry[1]), fh)
            os.replace(tmp, path)
        except Exception:
            pass
    _exports[key] = entry
    return entry


def call_stored(fn, jitted, *args):
    """``jitted(*args)`` (``jitted`` is ``fn`` jit-compiled), through the exported copy of
    ``fn`` for these arguments when
    [`enable_compilation_cache`][jurs.enable_compilation_cache] has turned the store on:
    loaded if an earlier process exported it, else exported and written. Falls back to
    ``jitted`` wherever exporting fails. For concrete arguments at top level only."""
    if _export_dir is None:
        return jitted(*args)
    import equinox as eqx
    import jax

    dynamic, static = eqx.partition(args, eqx.is_array)
    arrays, dynamic_tree = jax.tree.flatten(dynamic)
    entry = _load_or_export(fn, args, _export_key(fn, args), dynamic_tree, static)
    if entry is None:
        return jitted(*args)
    exported, skeleton = entry
    results = iter(exported.call(*arrays))
    parts, tree = jax.tree.flatten(skeleton)
    return tree.unflatten([next(results) if eqx.is_array(x) else x for x in parts])
