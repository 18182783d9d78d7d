"""``jurs fit`` on many clouds in one process: ``jurs fit a.csv b.csv ... -o out/`` (or a
folder, or a glob pattern) fits each file into its own sub-folder of ``out/``.

One process pays JAX's import and the compilation of the fit once: clouds whose padded
sizes share an octave (``jurs._problem.sizes``) on one grid reuse the compiled fit, so a
folder of scans costs about a warm fit each (docs/startup.md). Each sub-folder is written
whole or not at all (``write_outputs``, as a single fit); a file that fails is reported
on stderr and the others go on; the exit status is the largest of the files' statuses
(0 when every file was fitted).
"""

from __future__ import annotations

import argparse
import copy
import glob
import os
import sys
import time

from ._inputs import InputError, one_line, printable
from ._job import EXIT_BAD_INPUT, EXIT_FIT_FAILED

#: The suffixes of the clouds a folder given on the command line is searched for (those
#: ``jurs.datasets.load_points`` reads); other files in it are left alone.
CLOUD_FILE_SUFFIXES = (".csv", ".txt", ".npy", ".ply", ".obj", ".xyz", ".pts", ".stl", ".off")

_GLOB_CHARS = frozenset("*?[")


class FilesAction(argparse.Action):
    """Stores the cloud arguments as ``files`` (all of them) and ``file`` (the first: a
    single fit, and code that reads ``args.file``, sees one path as before)."""

    def __call__(self, parser, namespace, values, option_string=None):
        values = list(values or ())
        namespace.files = values
        namespace.file = values[0] if values else None


def is_batch(args) -> bool:
    """Whether ``args`` asks for a batch: several cloud arguments, a folder, or a glob
    pattern that names no file as it stands. One file keeps the single form (its outputs
    directly in ``--output``)."""
    files = getattr(args, "files", None) or [args.file]
    if len(files) > 1:
        return True
    (only,) = files
    return os.path.isdir(only) or (not os.path.exists(only) and _is_pattern(only))


def _is_pattern(text: str) -> bool:
    return any(c in _GLOB_CHARS for c in text)


def expand_inputs(arguments) -> list[str]:
    """The cloud files named by ``arguments``, in order: a folder gives its files with a
    suffix of ``CLOUD_FILE_SUFFIXES`` (sorted by name, not recursive), a glob pattern
    that is not itself a path gives its matches (sorted), anything else is taken as a file
    (a missing one is reported when it is read). A file named twice is fitted once."""
    found: list[str] = []
    for arg in arguments:
        if os.path.isdir(arg):
            names = sorted(os.listdir(arg))
            found += [
                os.path.join(arg, name)
                for name in names
                if name.lower().endswith(CLOUD_FILE_SUFFIXES)
                and os.path.isfile(os.path.join(arg, name))
            ]
        elif not os.path.exists(arg) and _is_pattern(arg):
            found += sorted(p for p in glob.glob(arg) if os.path.isfile(p))
        else:
            found.append(arg)
    seen, unique = set(), []
    for path in found:
        key = os.path.realpath(path)
        if key not in seen:
            seen.add(key)
            unique.append(path)
    return unique


def folder_names(paths) -> list[str]:
    """One output sub-folder name per path: the file's stem (``scan.csv`` -> ``scan``);
    where stems clash, the first keeps it and the later ones, in the order given, take
    ``stem-2``, ``stem-3``, ... (skipping names already taken), so a run with the same
    arguments always writes the same folders."""
    stems = [os.path.splitext(os.path.basename(os.path.normpath(p)))[0] or "cloud" for p in paths]
    taken = set(stems)
    used: set[str] = set()
    names = []
    for stem in stems:
        name, k = stem, 1
        while name in used or (name != stem and name in taken):
            k += 1
            name = f"{stem}-{k}"
        used.add(name)
        names.append(name)
    return names


def run_batch(args, run_one) -> int:
    """Fit every cloud of ``args.files`` (``expand_inputs``) into
    ``<args.output>/<folder_names(...)>`` with ``run_one`` (``jurs.cli.run_fit``) and the
    other options as given. A file that fails (bad input, a diverged fit, outputs that
    could not be written) is said on stderr and the next goes on; with a terminal on
    stderr (and without ``--quiet``) each file gets a progress line. Returns 0 when every
    file was fitted, else the largest exit status of a file (2: bad input, 1: a fit
    failed), after a summary line naming the failures."""
    paths = expand_inputs(args.files)
    if not paths:
        shown = ", ".join(printable(a) for a in args.files)
        print(
            f"jurs: error: {shown}: no cloud files ({', '.join(CLOUD_FILE_SUFFIXES)}) in "
            "this folder or pattern",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    out = args.output
    names = folder_names(paths)
    progress = not args.quiet and sys.stderr.isatty()
    failed: list[tuple[str, int]] = []
    start = time.perf_counter()
    for i, (path, name) in enumerate(zip(paths, names), 1):
        one = copy.copy(args)
        one.file, one.files, one.output = path, [path], os.path.join(out, name)
        if progress:
            print(
                f"jurs: [{i}/{len(paths)}] {printable(path)} -> {printable(one.output)}",
                file=sys.stderr,
                flush=True,
            )
        try:
            code = run_one(one)
        except InputError as exc:
            print(f"jurs: error: {printable(str(exc))}", file=sys.stderr)
            code = EXIT_BAD_INPUT
        except MemoryError:
            print(f"jurs: error: {printable(path)}: out of memory", file=sys.stderr)
            code = EXIT_FIT_FAILED
        except (ValueError, TypeError, OSError, ArithmeticError) as exc:
            # Anything else one cloud can raise: said, and the rest go on.
            print(f"jurs: error: {printable(path)}: {printable(one_line(exc))}", file=sys.stderr)
            code = EXIT_FIT_FAILED
        if code:
            failed.append((path, code))
    if not args.quiet or failed:
        done = len(paths) - len(failed)
        said = f"jurs: fitted {done} of {len(paths)} files in {time.perf_counter() - start:.1f} s"
        if failed:
            said += "; failed: " + ", ".join(printable(p) for p, _ in failed)
        print(said, file=sys.stderr if failed else sys.stdout)
    return max((code for _, code in failed), default=0)
