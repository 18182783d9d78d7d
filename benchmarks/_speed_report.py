"""The report of ``benchmarks/speed.py``: target verdicts, arithmetic bounds and the
markdown tables, rendered from the results JSON alone (so ``--from-json`` and the report
test reproduce ``speed.md`` without measuring anything)."""

from __future__ import annotations

from _common import LONG_CALL_S
from _speed_config import (
    ANALYSIS_RESOLUTION,
    CHAMFER_TOLERANCE,
    DENSE_LIMIT_BYTES,
    EXAMPLE4_MAX_STEPS,
    EXAMPLE4_TOL,
    IURS_STEP_PASSES,
    LSQ_LAM,
    MACS_PER_PASS,
    REFERENCE_POINTS,
    REFINED_REFERENCE_SAMPLES,
    REFINED_SAMPLES_PER_DIAGONAL,
    STEP_BUDGET_S,
    STEP_SOLVERS,
    TARGET_EX4_COLD_S,
    TARGET_EX4_WARM_S,
    TARGET_GRID,
    TARGET_IURS_PEAK_B,
    TARGET_IURS_STEP_S,
    TARGET_LSQ_S,
    TARGET_NORMAL_STEP_S,
    TARGET_POINTS,
    TARGET_RBF_POINTS,
    TARGET_RBF_RATIO,
)

# --------------------------------------------------------------------------- targets


def _find(rows, **keys):
    for r in rows:
        if all(r.get(k) == v for k, v in keys.items()):
            return r
    return None


def _verdict(value, limit, higher_is_better=False) -> str:
    if value is None:
        return "not measured"
    ok = value >= limit if higher_is_better else value <= limit
    return "PASS" if ok else "MISS"


def _target(label, measured, value, limit, required, higher_is_better=False) -> dict:
    return {
        "target": label,
        "measured": measured,
        "required": required,
        "verdict": _verdict(value, limit, higher_is_better),
        "value": value,
        "limit": limit,
    }


def _env_text(env: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in env.items())


def _step_target(label, measured, seconds, peak_b) -> dict:
    """An IURS-step target row under both limits: time and peak memory."""
    row = _target(
        label,
        measured,
        seconds,
        TARGET_IURS_STEP_S,
        f"<= {_ms(TARGET_IURS_STEP_S)}, <= {_gb(TARGET_IURS_PEAK_B)}",
    )
    if peak_b > TARGET_IURS_PEAK_B:
        row["verdict"] = "MISS"
    return row


def evaluate_targets(sweep, rbf, example4, bounds=(), tuned=None, fit_steps=None) -> list[dict]:
    """Each target: what was measured, the requirement and PASS/MISS (from measurements)."""
    big = _find(sweep, m=TARGET_POINTS, grid=TARGET_GRID) or {"iurs": {}, "lstsq": {}}
    where = f"{TARGET_POINTS:.0e} points, {_grid(TARGET_GRID)}"
    iurs, lsq = big["iurs"], big["lstsq"]
    step_bound = (_find(bounds, key="iurs_step") or {}).get("bound_s")
    bound_text = f"; arithmetic bound {_ms(step_bound)}" if step_bound else ""
    out = []
    in_fit = (fit_steps or {}).get("default", {})
    if "step_s" in in_fit:
        out.append(
            _step_target(
                f"IURS step inside jurs.fit, {where}, warm (fits of 1 and {1 + in_fit['steps']} "
                f"steps, difference of medians / {in_fit['steps']})",
                f"{_ms(in_fit['step_s'])} (from the fastest fits: {_ms(in_fit['step_min_s'])})"
                + (
                    "; compiled with jurs.COMPILER_OPTIONS, as jurs.fit does at this size"
                    if in_fit["compiler_options"]
                    else ""
                )
                + bound_text
                + f"; peak {_gb(in_fit['peak_over_base_b'])} over base (problem build included)",
                in_fit["step_s"],
                in_fit["peak_over_base_b"],
            )
        )
    if "loop_step_warm_s" in iurs:
        out.append(
            _target(
                f"IURS step in a jitted loop of {iurs['loop_steps']} steps (the state carried as "
                f"jurs.fit's loop carries it, no compiler options), {where}, warm (median / steps)",
                f"{_ms(iurs['loop_step_warm_s'])} (fastest loop: {_ms(iurs['loop_step_min_s'])})"
                + bound_text,
                iurs["loop_step_warm_s"],
                TARGET_IURS_STEP_S,
                f"<= {_ms(TARGET_IURS_STEP_S)}",
            )
        )
    out += [
        _target(
            f"IURS step called on its own (a jitted solver.step, no compiler options), "
            f"{where}, warm (median)",
            _ms(iurs.get("step_warm_s")) + bound_text,
            iurs.get("step_warm_s"),
            TARGET_IURS_STEP_S,
            f"<= {_ms(TARGET_IURS_STEP_S)}",
        ),
        _target(
            f"IURS peak memory, the step on its own, {where} (peak RSS minus RSS after "
            "imports and data)",
            f"{_gb(iurs.get('peak_over_base_b'))} (peak RSS {_gb(iurs.get('peak_b'))})",
            iurs.get("peak_over_base_b"),
            TARGET_IURS_PEAK_B,
            f"<= {_gb(TARGET_IURS_PEAK_B)}",
        ),
    ]
    for key, how in (
        ("iurs", "with {env} in the environment"),
        ("iurs_both", "compiled with jurs.COMPILER_OPTIONS, with {env}"),
    ):
        variant = (tuned or {}).get(key, {})
        if "step_warm_s" not in variant:
            continue
        out.append(
            _step_target(
                "The step on its own and its peak memory, "
                f"{how.format(env=_env_text(tuned['env']))}",
                f"{_ms(variant['step_warm_s'])}; {_gb(variant['peak_over_base_b'])} over base",
                variant["step_warm_s"],
                variant["peak_over_base_b"],
            )
        )
    out.append(_normal_ipia_target(sweep))
    out.append(
        _target(
            f"LeastSquares(lam={LSQ_LAM:g}) through jurs.fit, {where}, end to end incl. assembly",
            f"warm {_s(lsq.get('fit_warm_s'))}, first call {_s(lsq.get('fit_first_s'))}",
            lsq.get("fit_warm_s"),
            TARGET_LSQ_S,
            f"<= {_s(TARGET_LSQ_S)} (warm)",
        )
    )
    for ex4 in example4:
        label = (
            f"Full IURS fit: {ex4['label']}, {_grid(ex4['grid'])}, "
            f"tau={ex4['tau']:g}, lam={ex4['lam']:g}, tol={EXAMPLE4_TOL:g}"
        )
        warm = _target(
            label + ", warm",
            _ms(ex4.get("warm_s")) + _steps(ex4),
            ex4.get("warm_s"),
            TARGET_EX4_WARM_S,
            f"<= {_ms(TARGET_EX4_WARM_S)}",
        )
        bound = _find(bounds, label=ex4["label"])
        if bound and bound.get("bound_s") is not None:
            warm["measured"] += f"; arithmetic bound {_ms(bound['bound_s'])}"
            if bound["bound_s"] > TARGET_EX4_WARM_S:
                warm["verdict"] = "MISS (below the arithmetic bound)"
        floor = passes_floor_s(ex4)
        if floor is not None:
            warm["measured"] += f"; jurs's passes alone {_ms(floor)}"
            if floor > TARGET_EX4_WARM_S and warm["verdict"] == "MISS":
                warm["verdict"] = "MISS (jurs's passes alone exceed it)"
        out.append(warm)
        cached = ex4.get("cold_cached_s")
        out.append(
            _target(
                label + ", cold (first call in a fresh process, compile included)",
                _s(ex4.get("cold_s"))
                + _spread(ex4.get("cold_runs_s"))
                + (
                    ""
                    if cached is None
                    else f"; {_s(cached)} where JAX's persistent compilation cache holds "
                    "the fit from an earlier process" + _spread(ex4.get("cold_cached_runs_s"))
                ),
                ex4.get("cold_s"),
                TARGET_EX4_COLD_S,
                f"<= {_s(TARGET_EX4_COLD_S)}",
            )
        )
    out += _rbf_targets(rbf)
    return out


def _normal_ipia_target(sweep) -> dict:
    """NormalIPIA's step at the target grid, worst over m, in a jitted loop, as a solve
    runs it (a step called on its own, shown beside it, also copies the assembled stencil
    it returns in its state)."""
    rows = sorted(
        (r["m"], r["normal_ipia"])
        for r in sweep
        if r["grid"] == TARGET_GRID and "loop_step_warm_s" in r["normal_ipia"]
    )
    worst = max((res["loop_step_warm_s"] for _, res in rows), default=None)
    how = (
        "in a jitted loop of steps (median / steps; called on its own: "
        + ", ".join(f"{_ms(res['step_warm_s'])} at m = {m:.0e}" for m, res in rows)
        + ")"
    )
    measured = (
        f"{_ms(worst)} ("
        + ", ".join(f"{_ms(res['loop_step_warm_s'])} at m = {m:.0e}" for m, res in rows)
        + f"), {how}"
        if rows
        else "—"
    )
    return _target(
        f"NormalIPIA step, {_grid(TARGET_GRID)}, warm, worst over m",
        measured,
        worst,
        TARGET_NORMAL_STEP_S,
        f"<= {_ms(TARGET_NORMAL_STEP_S)}",
    )


def step_passes_s(ex4) -> float | None:
    """Seconds of one IURS step's passes over the samples, each timed alone
    (:func:`pass_times`): one F2, one F1 and two T2."""
    p = ex4.get("passes")
    return p["F2_s"] + p["F1_s"] + 2 * p["T2_s"] if p else None


def passes_floor_s(ex4) -> float | None:
    """The fit's steps times :func:`step_passes_s`: what jurs's kernels for the passes
    alone take over the fit, with no bookkeeping, dispatch or metrics."""
    step = step_passes_s(ex4)
    return step * ex4["num_steps"] if step is not None and "num_steps" in ex4 else None


def arithmetic_bounds(sweep, example4, ceiling) -> list[dict]:
    """Lower bounds on the warm time of the IURS targets from their arithmetic alone: steps
    x ``IURS_STEP_PASSES`` x ``MACS_PER_PASS`` x samples multiply-adds at the machine's
    measured rate (``ceiling``). The step count is the iteration's (eq. 38 at ``tol``), not
    the implementation's: an implementation of Algorithm 1 that computes at most at that rate
    cannot run faster on this machine."""
    rate = (ceiling or {}).get("macs_per_s")
    big = _find(sweep, m=TARGET_POINTS, grid=TARGET_GRID)
    rows = []
    if big and "step_warm_s" in big["iurs"]:
        rows.append(
            {
                "key": "iurs_step",
                "label": f"IURS step, {TARGET_POINTS:.0e} points, " + _grid(TARGET_GRID),
                "samples": 3 * TARGET_POINTS,
                "steps": 1,
                "measured_s": big["iurs"]["step_warm_s"],
                "target_s": TARGET_IURS_STEP_S,
            }
        )
    rows += [
        {
            "label": ex4["label"],
            "samples": 3 * ex4["points"],
            "steps": ex4["num_steps"],
            "measured_s": ex4["warm_s"],
            "target_s": TARGET_EX4_WARM_S,
        }
        for ex4 in example4
        if "num_steps" in ex4
    ]
    for r in rows:
        r["macs"] = r["steps"] * IURS_STEP_PASSES * MACS_PER_PASS * r["samples"]
        r["bound_s"] = r["macs"] / rate if rate else None
    return rows


def _given_label(options: dict, code: bool = False) -> str:
    q = "`" if code else ""
    return ", ".join(f"{q}{k}={v:g}{q}" for k, v in options.items())


def _accurate(j, b) -> bool:
    """jurs's refined Chamfer equal to or below the RBF's ("equal": within
    ``CHAMFER_TOLERANCE``)."""
    return j["refined_chamfer"] <= (1 + CHAMFER_TOLERANCE) * b["refined_chamfer"]


def _rbf_targets(rbf) -> list[dict]:
    """>= 100x faster than RBFInterpolator at 5000 points with equal or better Chamfer
    (the refined Chamfer, "equal" meaning within ``CHAMFER_TOLERANCE``): for the defaults,
    and for the fastest of the ``RBF_GIVEN`` settings that is as accurate as the RBF (or,
    if none is, the most accurate of them)."""
    r = _find(rbf, m=TARGET_RBF_POINTS)
    label = (
        f"jurs.fit(points, normals) defaults vs RBFInterpolator at {TARGET_RBF_POINTS} "
        "points on the same offset samples: fit-time ratio (warm jurs, automatic "
        "settings included), refined Chamfer to the exact curve"
    )
    required = f">= {TARGET_RBF_RATIO:.0f}x and Chamfer <= {1 + CHAMFER_TOLERANCE:g} x RBF's"
    if r is None or "rbf" not in r:
        done = [x for x in rbf if "rbf" in x]
        note = (
            (
                f"not run (largest m measured: {done[-1]['m']}, ratio "
                f"{_x(done[-1]['rbf']['fit_s'] / done[-1]['jurs_main']['warm_s'])})"
            )
            if done
            else "not run"
        )
        return [
            {"target": label, "measured": note, "required": required, "verdict": "not measured"}
        ]
    out = [_rbf_verdict(label, required, r["jurs_main"], r["rbf"])]
    given = r.get("jurs_given") or []
    if given:
        accurate = [j for j in given if _accurate(j, r["rbf"])]
        if accurate:
            best = min(accurate, key=lambda j: j["warm_s"])
            which = "the fastest of them as accurate as the RBF"
        else:
            best = min(given, key=lambda j: j["refined_chamfer"])
            which = "none as accurate as the RBF; the most accurate"
        out.append(
            _rbf_verdict(
                f"The same with settings given ({len(given)} tried, see the RBF section; {which}: "
                f"{_given_label(best['given'])}; for context: unsafe as defaults, see "
                "smoothing.md)",
                required,
                best,
                r["rbf"],
            )
        )
    return out


def _rbf_verdict(label, required, j, b) -> dict:
    ratio = b["fit_s"] / j["warm_s"]
    ok = ratio >= TARGET_RBF_RATIO and _accurate(j, b)
    return {
        "target": label,
        "measured": f"{_x(ratio)} (jurs first call: {_x(b['fit_s'] / j['first_s'])}); "
        f"Chamfer jurs {j['refined_chamfer']:.2e} vs RBF "
        f"{b['refined_chamfer']:.2e}, "
        f"{_x(j['refined_chamfer'] / b['refined_chamfer'])} the RBF's "
        f"(grid {_grid(j['grid'])})",
        "required": required,
        "verdict": "PASS" if ok else "MISS",
    }


# --------------------------------------------------------------------------- report


def _ms(s):
    """Seconds as ms below one second (3 significant digits)."""
    return "—" if s is None else (f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s")


def _range(runs) -> str:
    """``low-high`` of a list of per-process times."""
    return f"{_s(min(runs))}-{_s(max(runs))}"


def _spread(runs) -> str:
    """`` (median of n processes: low-high)`` for a list of per-process times."""
    if not runs or len(runs) < 2:
        return ""
    return f" (median of {len(runs)} processes: {_range(runs)})"


def _us(s):
    return "—" if s is None else f"{s * 1e6:.3g} us"


def _s(s):
    return "—" if s is None else f"{s:.3g} s"


def _gb(b):
    if b is None:
        return "—"
    return f"{b / 2**30:.2f} GiB" if abs(b) >= 2**30 else f"{b / 2**20:.0f} MiB"


def _steps(r):
    return f" ({r['num_steps']} steps, {r['result']})" if "num_steps" in r else ""


def _x(ratio):
    """A speed ratio: 2 significant digits, so that 0.61x does not print as 1x."""
    return "—" if ratio is None else f"{ratio:.2g}x" if ratio < 100 else f"{ratio:.0f}x"


def _table(header, rows):
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def _err(res):
    return f"error: {res['error'][:80]}" if "error" in res else None


def _grid(grid) -> str:
    """``128`` -> ``128x128``; ``(92, 96)`` -> ``92x96``."""
    return "x".join(map(str, grid)) if isinstance(grid, (list, tuple)) else f"{grid}x{grid}"


def _where(r) -> list:
    """The m and grid cells of a sweep row."""
    return [f"{r['m']:.0e}", _grid(r["grid"])]


def _measured_row(cells, res, width: int, values) -> list:
    """``cells``, then ``values()`` (``width`` cells), or ``res``'s error padded to ``width``."""
    return cells + ([_err(res)] + [""] * (width - 1) if _err(res) else values())


def report(data: dict) -> str:
    """The markdown report (also printed)."""
    lines = [
        f"# Speed{' (QUICK run: small sizes only)' if data['quick'] else ''}",
        "",
        f"Machine: {data['machine']}. Device of the measurements: {data['device']}. "
        f"float64. Whole run: {data['runtime_s'] / 60:.1f} min."
        + _probe_text(data.get("ceiling"), data.get("ceiling_start")),
        "",
        "Load average when the run began (other work on the machine, before this "
        "run added its own): "
        + (f"{data['load_average']:.1f}" if "load_average" in data else "not recorded")
        + ". Timings taken beside other work are indicative.",
        "",
    ]
    lines += [f"Note: {n}" for n in data.get("notes", [])] + [""] * bool(data.get("notes"))
    lines += ["## Targets", ""]
    loop_note = (
        "* **In a loop**: the same step run `k` times in one jitted `fori_loop` that "
        "carries the state, as the driver's loop in `jurs.fit` does (median and fastest "
        "loop, divided by `k`; `k` gives a loop of about 50 ms, 5 to 200 steps). A step "
        "called on its own returns its whole state in fresh buffers; a loop updates its "
        "carry in place. NormalIPIA's state holds the assembled stencil (6.4 MB at "
        "128 x 128), which a step called on its own copies every call."
    )
    lines += _table(
        ["target", "measured", "required", "verdict"],
        [[t["target"], t["measured"], t["required"], t["verdict"]] for t in data["targets"]],
    )
    lines += [
        "",
        "## What is measured",
        "",
        "* Data: the paper's Example 1 curve, `jurs.datasets.example1(m)`; 3m samples "
        "(points and both offsets, d = 0.1, eps = 0.01), box = bounding box + 10 %.",
        "* **Warm step**: median time of a jitted `solver.step(problem, state)` on a state "
        "one step in (weights already moved), as in `benchmarks/step_speed.py`; "
        "**compile** = first call minus warm (the jit cache is cleared first). Repeats: "
        f"until about {STEP_BUDGET_S:g} s are spent, at least 3 (2 after a first call "
        f"above that, 1 after one above {LONG_CALL_S:g} s), at most 20; the minimum is "
        "shown in brackets "
        "(closest to an unshared machine).",
        loop_note,
        "* **NormalIPIA assembly**: its `init` (D^T D as a 49-point stencil and D^T b), "
        "warm, and its first call (with compilation), apart from its step.",
        f"* **LeastSquares**: `jurs.fit(points, normals, grid, solver=LeastSquares("
        f"lam={LSQ_LAM:g}))` from NumPy arrays to the solved spline: problem building "
        "(host-side sample layout), assembly and linear solve; first call (compiles) "
        "and warm (median).",
        "* **Peak memory**: every measurement runs in a fresh subprocess; *peak* is its "
        "peak resident set size (VmHWM), *over base* is the peak minus the RSS after "
        "imports, JAX start-up and data creation, i.e. the memory the problem build, "
        "the init, XLA compilation and the timed calls took at their worst (at small "
        "sizes compilation dominates it). Host memory only"
        + (
            "; the device's own peak is in the JSON."
            if data["device"].split(":")[0] != "cpu"
            else "."
        ),
        "* Grid sweep: "
        + "; ".join(
            f"m = {int(m):.0e}: {', '.join(map(str, g))}" for m, g in data["sweep_config"].items()
        )
        + " (pruned: fine grids on few points, and part of the rest to keep the run "
        "short; the 1e6 x 8 x 8 point is there for the NumPy baseline).",
        "",
    ]
    lines += _sweep_tables(data["sweep"])
    lines += _port_table(data["port"])
    lines += _rbf_table(data["rbf"])
    lines += _example4_table(data["example4"])
    lines += _bounds_table(data.get("bounds", []), data.get("ceiling"))
    lines += _tuned_table(data.get("tuned"), data["sweep"], data.get("fit_steps"))
    return "\n".join(lines) + "\n"


def _probe_text(ceiling, ceiling_start) -> str:
    """The machine's speed in this run, by which runs compare (it moves between runs): the
    probe at its start and at its end (the end alone where the first probe failed)."""
    if not ceiling or "macs_per_s" not in ceiling:
        return ""

    def rate(probe):
        return f"{probe['macs_per_s'] / 1e9:.3g} G multiply-adds/s"

    text = f" Machine speed in this run: a float64 matrix product of side {ceiling['n']} reached "
    if ceiling_start and "macs_per_s" in ceiling_start:
        return text + (
            f"{rate(ceiling_start)} at the start of the run and {rate(ceiling)} at "
            "its end (compare runs by it)."
        )
    return text + f"{rate(ceiling)} (measured at the end of the run; compare runs by it)."


def _sweep_tables(sweep) -> list[str]:
    lines = []
    for key, (label, _, _) in STEP_SOLVERS.items():
        extra = ["assembly (init) warm", "assembly first call"] if key == "normal_ipia" else []
        rows = []
        for r in sweep:
            res = r[key]
            rows.append(
                _measured_row(
                    _where(r),
                    res,
                    7 + len(extra),
                    lambda: (
                        [
                            f"{_ms(res['step_warm_s'])} ({_ms(res['step_min_s'])})",
                            f"{_ms(res['loop_step_warm_s'])} ({_ms(res['loop_step_min_s'])})",
                            res["loop_steps"],
                            _s(res["step_compile_s"]),
                            _gb(res["peak_over_base_b"]),
                            _gb(res["peak_b"]),
                            _s(res["build_s"]),
                        ]
                        + ([_ms(res["init_warm_s"]), _s(res["init_first_s"])] if extra else [])
                    ),
                )
            )
        lines += [f"## {label}: one step", ""]
        lines += _table(
            [
                "m",
                "grid",
                "warm step (min)",
                "in a loop: step (min)",
                "loop steps",
                "compile",
                "peak over base",
                "peak RSS",
                "problem build",
            ]
            + extra,
            rows,
        )
        lines.append("")
    rows = []
    for r in sweep:
        res = r["lstsq"]
        rows.append(
            _measured_row(
                _where(r),
                res,
                6,
                lambda: [
                    f"{_s(res['fit_warm_s'])} ({_s(res['fit_min_s'])})",
                    _s(res["fit_first_s"]),
                    _gb(res["peak_over_base_b"]),
                    _gb(res["peak_b"]),
                    res.get("result", "—"),
                    f"{res['E_ave']:.2e}",
                ],
            )
        )
    lines += [f"## LeastSquares(lam={LSQ_LAM:g}) end to end through jurs.fit", ""]
    lines += _table(
        ["m", "grid", "warm (min)", "first call", "peak over base", "peak RSS", "result", "E_ave"],
        rows,
    )
    return lines + [""]


def _port_table(port_rows) -> list[str]:
    lines = [
        "## Baseline: the paper's Algorithm 1 in NumPy (dense D rebuilt every step)",
        "",
        "`benchmarks/_numpy_port.py`: dense B (3m x NM) from "
        "`scipy.interpolate.BSpline.design_matrix` once; per step W = B w, "
        "D = B * w / W, mu = 2 / max column sum of D, eq. 33 and the weight gradient "
        "(its iterates equal jurs.IURS's: `tests/test_numpy_port.py`). Same tau = 1e-2, "
        f"lam = 1e-3. Run where one dense matrix is <= {DENSE_LIMIT_BYTES / 1e9:g} GB.",
        "",
    ]
    rows = []
    for r in port_rows:
        p = r["port"]
        rows.append(
            _measured_row(
                _where(r) + [_gb(r["dense_b"])],
                p,
                5,
                lambda: [
                    _s(p["build_s"]),
                    _ms(p["step_warm_s"]),
                    _ms(r["jurs_iurs_step_s"]),
                    _x(r["ratio"]),
                    _gb(p["peak_over_base_b"]),
                ],
            )
        )
    lines += _table(
        [
            "m",
            "grid",
            "one dense matrix",
            "build B",
            "NumPy step",
            "jurs IURS step",
            "NumPy / jurs",
            "NumPy peak over base",
        ],
        rows,
    )
    return lines + [""]


def _unconverged(rbf_rows) -> int:
    """Points of the refined distances whose projection onto a zero set did not converge,
    over every fit and RBF of the comparison."""
    fits = [
        r[k]
        for r in rbf_rows
        if not _err(r) and "skipped" not in r
        for k in ("jurs_main", "jurs_coarse", "rbf")
    ]
    fits += [g for r in rbf_rows for g in r.get("jurs_given") or []]
    return sum(f.get("unconverged", 0) for f in fits)


def _rbf_table(rbf_rows) -> list[str]:
    lines = [
        "## Baseline: scipy RBFInterpolator (thin-plate) vs jurs defaults",
        "",
        "Example 1 with m points. jurs: `jurs.fit(points, normals)`, every setting "
        "automatic (grid, d, eps, lambda; `LeastSquares`), timed with the automatic "
        "settings included. RBF: `benchmarks/_baselines.rbf_fit` on the same 3m offset "
        "samples and targets (the d and eps the defaults chose; fit time = the dense "
        "solve; evaluation not timed). Both zero sets are sampled on the default fit's "
        f"box at resolution {ANALYSIS_RESOLUTION} and measured with "
        "`jurs.levelset.analyze_grid` (as `rbf_report` does): components, all / "
        "supplementary (more than half the length farther than 2 d from the data), and "
        "the *analysis* Chamfer, which resamples the contour at half a grid cell: a floor "
        "of about 1.5e-3 under any fit. **Refined** Chamfer and Hausdorff (the target's "
        "measure): `jurs.levelset.refined_chamfer_hausdorff`, no sampling floor. The "
        f"contour, resampled at {REFINED_SAMPLES_PER_DIAGONAL} points per box diagonal, is "
        "moved onto the zero set by Newton steps (jurs: the spline's gradient; RBF: "
        "central differences) and measured to the segments of "
        f"{REFERENCE_POINTS} samples of the exact curve, and "
        f"{REFINED_REFERENCE_SAMPLES} of those are projected onto the zero set. Contour "
        "points measured without the projection, however densely resampled, carry "
        "marching squares' own error, about 1e-5 here, under which accurate fits tie. "
        "Last column, for context: jurs with the same settings on the coarser grid G. "
        f"Projections that did not converge (then measured where they ended): "
        f"{_unconverged(rbf_rows)} in this table.",
        "",
    ]
    rows = []
    for r in rbf_rows:
        if _err(r) or "skipped" in r:
            rows.append([r["m"], _err(r) or f"skipped: {r['skipped']}"] + [""] * 10)
            continue
        j, b, c = r["jurs_main"], r["rbf"], r["jurs_coarse"]
        rows.append(
            [
                r["m"],
                _grid(j["grid"]),
                f"{j['offset']:.3g}",
                _s(b["fit_s"]),
                _ms(j["warm_s"]),
                _s(j["first_s"]),
                f"{_x(b['fit_s'] / j['warm_s'])} / {_x(b['fit_s'] / j['first_s'])}",
                f"{j['refined_chamfer']:.2e} / {b['refined_chamfer']:.2e}",
                f"{j['refined_hausdorff']:.2e} / {b['refined_hausdorff']:.2e}",
                f"{j['chamfer']:.2e} / {b['chamfer']:.2e}",
                f"{j['num_components']}/{j['num_supplementary']} vs "
                f"{b['num_components']}/{b['num_supplementary']}",
                f"{_grid(c['grid'])}: {c['refined_chamfer']:.2e}, "
                f"{c['num_components']}/{c['num_supplementary']}, {_ms(c['warm_s'])} "
                f"({_x(b['fit_s'] / c['warm_s'])})",
            ]
        )
    lines += _table(
        [
            "m",
            "jurs grid",
            "d",
            "RBF fit",
            "jurs warm",
            "jurs first call",
            "RBF / jurs (warm / first)",
            "refined Chamfer jurs / RBF",
            "refined Hausdorff jurs / RBF",
            "analysis Chamfer jurs / RBF",
            "components jurs vs RBF",
            "coarser grid G: refined Chamfer, components, warm (RBF / it)",
        ],
        rows,
    )
    for r in rbf_rows:
        if not r.get("jurs_given") or _err(r):
            continue
        b = r["rbf"]
        lines += [
            "",
            f"At m = {r['m']}, jurs with settings given (the rest automatic, timed "
            "too): finer grids and smoothings far below the default. Such smoothings "
            "grow supplementary components on glyphs and traced outlines "
            "(`benchmarks/results/smoothing.md`), so the defaults do not use them. "
            f"The RBF: refined Chamfer {b['refined_chamfer']:.2e}, Hausdorff "
            f"{b['refined_hausdorff']:.2e}, fit {_s(b['fit_s'])}.",
            "",
        ]
        rows = [
            [
                _given_label(e["given"], code=True),
                _grid(e["grid"]),
                f"{e['lam']:.3g}",
                _ms(e["warm_s"]),
                _x(b["fit_s"] / e["warm_s"]),
                f"{e['refined_chamfer']:.2e} ({_x(e['refined_chamfer'] / b['refined_chamfer'])})",
                f"{e['refined_hausdorff']:.2e}",
                f"{e['num_components']}/{e['num_supplementary']}",
            ]
            for e in r["jurs_given"]
        ]
        lines += _table(
            [
                "given",
                "grid",
                "lambda",
                "jurs warm",
                "RBF / jurs",
                "refined Chamfer (x the RBF's)",
                "refined Hausdorff",
                "components",
            ],
            rows,
        )
    return lines + [""]


def _example4_table(rows_in) -> list[str]:
    lines = [
        "## Full regularised IURS fits of Example-4 size",
        "",
        f"`jurs.fit(points, normals, grid=15, solver=IURS(tau, lam, tol={EXAMPLE4_TOL:g}, "
        f"max_steps={EXAMPLE4_MAX_STEPS}))` on `jurs.shapes.get(shape, points)`. Cold: "
        "the first call in a fresh process, compilation included (imports timed apart); "
        "warm: median of later calls. Each fit runs in several fresh processes: cold and "
        "warm are the medians over them, with the range of the cold times and the fastest "
        "warm call. *Cold, cache filled*: the same first call where JAX's persistent "
        "compilation cache (`JAX_COMPILATION_CACHE_DIR`, with "
        "`JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0`) holds the fit, compiled by one "
        "process before these: the process loads it instead of compiling it (median and "
        "range over as many processes).",
        "",
    ]
    rows = []
    for r in rows_in:
        cells = [r["label"], _grid(r["grid"]), f"{r['tau']:g}", f"{r['lam']:g}"]
        runs = r.get("cold_runs_s") or []
        cached_runs = r.get("cold_cached_runs_s") or []
        cached = f"{_s(r['cold_cached_s'])} ({_range(cached_runs)})" if cached_runs else "—"
        rows.append(
            _measured_row(
                cells,
                r,
                8,
                lambda: [
                    r["num_steps"],
                    r["result"],
                    f"{_ms(r['warm_s'])} ({_ms(r['min_s'])})",
                    _s(r["cold_s"]),
                    _range(runs) if runs else "—",
                    cached,
                    _s(r["import_s"]),
                    f"{r['E_ave']:.2e}",
                ],
            )
        )
    lines += _table(
        [
            "fit",
            "grid",
            "tau",
            "lam",
            "steps",
            "result",
            "warm (fastest)",
            "cold",
            "cold range",
            "cold, cache filled (range)",
            "imports",
            "E_ave",
        ],
        rows,
    )
    timed = [r for r in rows_in if r.get("passes") and "num_steps" in r]
    if not timed:
        return lines + [""]
    lines += [
        "",
        "Where the warm time goes: the passes over the samples that every IURS step "
        "makes, each timed alone in a jitted loop of "
        f"{timed[0]['passes']['repeats']} passes (fastest run), as jurs's kernels run "
        "them. F2: W and F(wC) at the new weights (eq. 14); F1: F(wC) at the new C "
        "(eq. 35); T2: D^T r with D's column sums (eqs. 33, 25), and the two sums of "
        "the weight gradient (eq. 19). Times the fit's steps they are a floor for "
        "these kernels, with no bookkeeping, dispatch or metrics; not a floor for "
        "the method (see the arithmetic bounds below).",
        "",
    ]
    rows = [
        [
            r["label"],
            _us(r["passes"]["F2_s"]),
            _us(r["passes"]["F1_s"]),
            _us(r["passes"]["T2_s"]),
            _us(step_passes_s(r)),
            _us(r["warm_s"] / r["num_steps"]),
            _ms(passes_floor_s(r)),
            _ms(r["warm_s"]),
        ]
        for r in timed
    ]
    lines += _table(
        [
            "fit",
            "F2",
            "F1",
            "T2",
            "a step's passes (F2 + F1 + 2 T2)",
            "warm fit / steps",
            "passes x steps",
            "warm fit",
        ],
        rows,
    )
    return lines + [""]


def _bounds_table(bounds, ceiling) -> list[str]:
    if not bounds or not ceiling or "macs_per_s" not in ceiling:
        return []
    lines = [
        "## Lower bounds from the arithmetic of Algorithm 1",
        "",
        "An IURS step as eqs. 19-35 define it applies the collocation D (eq. 23) or its "
        f"transpose at least {IURS_STEP_PASSES} times, each {MACS_PER_PASS} multiply-adds "
        "a sample: W and F(wC) at the new weights (eq. 14), D^T r and D's column sums "
        "(eqs. 33 and 25), F(wC) at the new C for the energy (eq. 35), and the weight "
        "gradient at the new (C, w) for the next step (eq. 19). Nothing else is counted: "
        "no division, gather, scatter or memory traffic. At the machine's measured "
        f"multiply-add rate, a float64 NumPy matrix product of side {ceiling['n']} on "
        f"every core ({ceiling['macs_per_s'] / 1e9:.3g} G multiply-adds/s, the rate tuned "
        "BLAS code reaches on this machine), a fit takes at least steps x that "
        "arithmetic; the steps are the iteration's "
        f"(eq. 38 at tol = {EXAMPLE4_TOL:g}), not the implementation's. Where the bound "
        "exceeds the target, no implementation of the paper's method that computes at most "
        "as fast as tuned BLAS meets it here.",
        "",
    ]
    rows = [
        [
            b["label"],
            b["samples"],
            b["steps"],
            f"{b['macs']:.3g}",
            _ms(b["bound_s"]),
            _ms(b["target_s"]),
            _ms(b["measured_s"]),
            "target below the bound" if b["bound_s"] > b["target_s"] else "not excluded",
        ]
        for b in bounds
    ]
    lines += _table(
        [
            "what",
            "samples",
            "steps",
            "multiply-adds",
            "bound",
            "target",
            "measured (warm)",
            "verdict of the bound",
        ],
        rows,
    )
    return lines + [""]


def _tuned_table(tuned, sweep, fit_steps=None) -> list[str]:
    big = _find(sweep, m=TARGET_POINTS, grid=TARGET_GRID)
    if not tuned or not big:
        return []
    env = _env_text(tuned["env"])
    lines = [
        "## Large problems: huge pages and compiler options",
        "",
        f"The same workers at {TARGET_POINTS:.0e} points, {_grid(TARGET_GRID)}. "
        f"*Huge pages*: `{env}` in the environment, so glibc's malloc, from which "
        "XLA's CPU buffers come, asks for transparent huge pages (glibc >= 2.35; Linux "
        "THP in `madvise` or `always` mode); with 4 KB pages every call page-faults its "
        "fresh buffers in again. glibc reads it at start-up: a setting of the process, "
        "not of the library. *Options*: the step jitted with `jurs.COMPILER_OPTIONS` "
        "(as `jurs.fit` compiles large problems: floating-point reassociation, so LLVM "
        "vectorises the per-bucket sums; "
        "NaN, Inf, division and functions keep IEEE semantics). *Page faults*: minor "
        "faults of one warm step.",
        "",
    ]
    variants = [
        ("IURS step", big["iurs"]),
        ("IURS step, huge pages", tuned["iurs"]),
        ("IURS step, options", tuned.get("iurs_options", {})),
        ("IURS step, huge pages and options", tuned.get("iurs_both", {})),
    ]
    rows = [
        _measured_row(
            [name],
            r,
            3,
            lambda r=r: [
                f"{_ms(r['step_warm_s'])} ({_ms(r['step_min_s'])})",
                r.get("step_page_faults", "—"),
                _gb(r["peak_over_base_b"]),
            ],
        )
        for name, r in variants
        if r
    ]
    for name, r in (
        (f"LeastSquares(lam={LSQ_LAM:g}) fit", big["lstsq"]),
        (f"LeastSquares(lam={LSQ_LAM:g}) fit, huge pages", tuned["lstsq"]),
    ):
        rows.append(
            _measured_row(
                [name],
                r,
                3,
                lambda r=r: [
                    f"{_s(r['fit_warm_s'])} ({_s(r['fit_min_s'])})",
                    "—",
                    _gb(r["peak_over_base_b"]),
                ],
            )
        )
    lines += _table(["measurement", "warm (min)", "page faults", "peak over base"], rows)
    lines += _fit_steps_table(fit_steps)
    return lines + [""]


def _fit_steps_table(fit_steps) -> list[str]:
    if not fit_steps:
        return []
    env = _env_text(fit_steps["env"])
    lines = [
        "",
        "**The step inside a fit.** `jurs.fit(points, normals, grid, solver=IURS("
        "tau=1e-2, lam=1e-3, tol=0, max_steps=n), offset, eps)` end to end for n = 1 and "
        "n = 1 + k; a step costs the difference of the warm medians over k. The fit's "
        "steps run in one compiled loop, whose buffers are allocated and page-faulted "
        "once per call, not per step; at this size `jurs.fit` compiles its own solvers "
        "with `jurs.COMPILER_OPTIONS` (column *options*). *Page faults*: minor faults "
        "of one warm fit call.",
        "",
    ]
    rows = []
    for name, r in (("as it is", fit_steps["default"]), (f"with {env}", fit_steps["hugepages"])):
        rows.append(
            _measured_row(
                [name],
                r,
                7,
                lambda r=r: [
                    "yes" if r["compiler_options"] else "no",
                    r["steps"],
                    f"{_ms(r['step_s'])} ({_ms(r['step_min_s'])})",
                    _ms(r["fits"]["1"]["warm_s"]),
                    _ms(r["fits"][str(1 + r["steps"])]["warm_s"]),
                    f"{r['fits']['1']['page_faults']} / "
                    f"{r['fits'][str(1 + r['steps'])]['page_faults']}",
                    _gb(r["peak_over_base_b"]),
                ],
            )
        )
    lines += _table(
        [
            "environment",
            "options",
            "k",
            "step (from fastest fits)",
            "fit, 1 step",
            "fit, 1 + k steps",
            "page faults (1 / 1 + k steps)",
            "peak over base",
        ],
        rows,
    )
    return lines
