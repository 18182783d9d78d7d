"""The real-data benchmark's pieces: the ring-by-ring topology match on circles, a traced case
(deterministic, pixel staircase kept), the variants' outliers, and the markdown renderer."""

import numpy as np
import pytest

import jurs.shapes

from .. import _realdata_cases as cases
from .. import realdata


def circle(cx=0.0, cy=0.0, r=1.0, n=400):
    """A closed polyline (first vertex repeated) around ``(cx, cy)``."""
    t = np.linspace(0.0, 2 * np.pi, n + 1)
    return np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1)


def band(t0, t1, r=1.0, width=0.01, n=200):
    """A thin closed loop along the arc ``t0..t1`` of the circle of radius ``r``."""
    t = np.linspace(t0, t1, n)
    out = np.stack([(r + width) * np.cos(t), (r + width) * np.sin(t)], axis=1)
    back = np.stack([(r - width) * np.cos(t), (r - width) * np.sin(t)], axis=1)[::-1]
    return np.vstack([out, back, out[:1]])


def counts(t):
    return {k: t[k] for k in ("matched", "split", "merged", "lost", "partial", "extra")}


TOL = 0.05


def test_one_to_one_rings_match_exactly():
    rings = [circle(-2), circle(2, r=0.5)]
    comps = [circle(2, r=0.52), circle(-2, r=1.02)]  # order does not matter
    t = realdata.match_rings(rings, comps, TOL)
    assert t["exact"] and t["matched"] == 2 and t["extra"] == 0
    assert t["component_rings"] == [[1], [0]]


def test_a_ring_followed_by_two_components_is_split():
    t = realdata.match_rings([circle()], [band(0.0, np.pi), band(np.pi, 2 * np.pi)], TOL)
    assert counts(t) == {**counts(t), "split": 1, "matched": 0, "extra": 0}
    assert not t["exact"]


def test_a_piece_pinched_off_a_ring_splits_it_but_a_tiny_loop_is_extra():
    main = band(0.1 * np.pi, 2 * np.pi)  # 95 % of the ring
    piece = band(0.0, 0.1 * np.pi)  # 5 %, longer than the tolerance
    t = realdata.match_rings([circle()], [main, piece], TOL)
    assert t["split"] == 1 and t["extra"] == 0 and t["ring_status"] == ["split"]
    tiny = band(0.0, 0.003 * np.pi, width=0.003)  # shorter than the tolerance
    t = realdata.match_rings([circle()], [main, tiny], TOL)
    assert t["ring_status"] == ["matched"] and t["extra"] == 1


def test_one_component_along_two_rings_merges_them():
    """Two unit circles 0.1 apart, fitted by one loop around both (the outline of the union
    of two slightly larger circles)."""
    rings = [circle(-1.05), circle(1.05)]
    t = np.linspace(0, 2 * np.pi, 2000)
    xy = np.stack([np.cos(t), np.sin(t)], 1) * 1.06
    left, right = xy + [-1.05, 0], xy + [1.05, 0]
    union = np.vstack([left[left[:, 0] < 0], right[right[:, 0] > 0]])
    union = union[np.argsort(np.arctan2(union[:, 1], union[:, 0]))]
    t = realdata.match_rings(rings, [np.vstack([union, union[:1]])], 0.1)
    assert t["merged"] == 2 and t["matched"] == 0 and t["component_rings"] == [[0, 1]]


def test_a_ring_without_component_is_lost_even_next_to_a_matched_one():
    """The second ring lies within the tolerance of the first one's component, but that
    component is nearer its own ring all along: the second ring is lost, not merged."""
    rings = [circle(), circle(r=1.03)]
    t = realdata.match_rings(rings, [circle(r=0.995)], TOL)
    assert t["ring_status"] == ["matched", "lost"]
    assert not t["exact"]


def test_a_component_along_no_ring_is_extra():
    t = realdata.match_rings([circle()], [circle(r=1.01), circle(5, 5, 0.3)], TOL)
    assert t["matched"] == 1 and t["extra"] == 1 and not t["exact"]
    assert t["component_rings"] == [[0], []]


def test_a_tiny_loop_on_the_ring_is_extra():
    tiny = circle(1.0, 0.0, 0.004, n=8)
    t = realdata.match_rings([circle()], [circle(r=1.01), tiny], TOL)
    assert t["ring_status"] == ["matched"] and t["extra"] == 1


def test_a_component_following_part_of_a_ring_is_partial():
    t = realdata.match_rings([circle()], [band(0.0, 0.8 * np.pi)], TOL)
    assert t["ring_status"] == ["partial"]


def test_no_components_loses_every_ring():
    t = realdata.match_rings([circle(), circle(3)], [], TOL)
    assert t["lost"] == 2 and t["components"] == 0 and not t["exact"]


def test_traced_case_is_deterministic_and_keeps_the_pixel_staircase():
    a = cases.trace(cases.blobs())
    b = cases.trace(cases.blobs())
    assert len(a) == len(b) > 3
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    for comp in a:
        twice = 2 * comp
        assert np.allclose(twice, np.round(twice))  # on the half-pixel lattice
        half = np.abs(comp - np.round(comp)) > 0.25
        assert np.all(half.sum(axis=1) == 1)  # one coordinate on a pixel edge, one mid-edge
        # marching squares on a 0/1 mask: steps across a cell corner or straight through a
        # cell, nothing else (no blur); both kinds occur on a curved outline (the staircase)
        steps = {tuple(s) for s in np.abs(np.diff(np.vstack([comp, comp[:1]]), axis=0))}
        assert steps <= {(0.5, 0.5), (1.0, 0.0), (0.0, 1.0)} and (0.5, 0.5) in steps
    case = cases.build("blobs")
    assert case.traced and len(case.components) == len(jurs.shapes.orient(a))
    allp = np.concatenate(case.components)
    assert np.ptp(allp, axis=0).max() == pytest.approx(cases.SIZE)
    assert cases.M_MIN <= case.m <= cases.M_MAX
    assert case.m == int(round(cases.POINTS_PER_PIXEL * case.length_px, -2))


def _circle_case(m=400):
    ring = circle(n=2000)[:-1] * 4.0
    return cases.Case("circle", "test", False, (ring,), (ring,), 0.02, None, 1000.0, m)


def test_outlier_variant_moves_far_points_with_unit_normals():
    case = _circle_case()
    ref = realdata.reference_samples(case)
    p, n, moved = realdata.cloud(case, "outlier", ref)
    assert len(moved) == round(realdata.OUTLIERS * case.m)
    r = np.linalg.norm(p[moved], axis=1)
    assert np.all(np.abs(r - 4.0) > realdata.OUTLIER_MIN_DIST * case.diag - 1e-3)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    rest = np.setdiff1d(np.arange(case.m), moved)
    assert np.allclose(np.linalg.norm(p[rest], axis=1), 4.0, atol=1e-3)
    p2, _, moved2 = realdata.cloud(case, "outlier", ref)
    assert np.array_equal(p, p2) and np.array_equal(moved, moved2)  # seeded


def test_noisy_variant_perturbs_positions_and_turns_normals():
    case = _circle_case()
    ref = realdata.reference_samples(case)
    p0, n0, _ = realdata.cloud(case, "clean", ref)
    p, n, _ = realdata.cloud(case, "noisy", ref)
    sigma = np.std(p - p0)
    assert sigma == pytest.approx(realdata.NOISE * case.diag, rel=0.15)
    angle = np.arccos(np.clip(np.sum(n * n0, axis=1), -1, 1))
    assert np.sqrt(np.mean(angle**2)) == pytest.approx(realdata.NORMAL_NOISE, rel=0.15)


def _run(case, variant, *, exact, hausdorff, chamfer, rbf_chamfer, warm_s, m=2000):
    topo = {
        "matched": 3 if exact else 1,
        "split": 0,
        "merged": 0 if exact else 2,
        "lost": 0,
        "partial": 0,
        "extra": 0 if exact else 1,
        "rings": 3,
        "components": 3 if exact else 2,
        "exact": exact,
        "ring_status": ["matched"] * 3 if exact else ["matched", "merged", "merged"],
        "component_rings": [[0], [1], [2]] if exact else [[0], [1, 2]],
    }
    fit = {"chamfer": chamfer, "hausdorff": hausdorff, "topology": topo}
    return {
        "case": case,
        "variant": variant,
        "m": m,
        "rings": 3,
        "diag": 10.0,
        "settings": {"grid": [64, 48], "smoothing": 1e-6, "offset": 0.02, "noise": 0.001},
        "jurs": {**fit, "status": "successful", "warm_s": warm_s, "first_s": 2.0},
        "rbf": {
            "chamfer": rbf_chamfer,
            "hausdorff": 0.004,
            "topology": {**topo, "exact": True, "matched": 3, "merged": 0, "extra": 0},
            "points": min(m, 4000),
            "fit_s": 3.0,
        },
        "chamfer_ratio": chamfer / rbf_chamfer,
    }


def test_markdown_counts_the_runs_meeting_each_target():
    runs = [
        _run("a", "clean", exact=True, hausdorff=0.003, chamfer=1e-4, rbf_chamfer=2e-4, warm_s=0.1),
        _run("a", "noisy", exact=False, hausdorff=0.02, chamfer=3e-4, rbf_chamfer=2e-4, warm_s=0.2),
        _run("b", "clean", exact=True, hausdorff=0.006, chamfer=1e-4, rbf_chamfer=2e-4, warm_s=1.0),
        {"case": "b", "variant": "noisy", "m": 20000, "error": "ValueError: boom"},
    ]
    info = {"rings": 3, "length_px": 1200.0, "m": 2000, "pixel": 0.04, "diag": 10.0}
    meta = {
        "date": "2026-01-01",
        "quick": True,
        "machine": "test",
        "load_average": 0.5,
        "command": "python -m benchmarks.realdata --quick",
        "cases": ["a", "b"],
        "variants": ["clean", "noisy"],
        "case_info": {k: {**info, "source": f"'il1{k}|' source"} for k in "ab"},
        "total_s": 120.0,
        "figure": "worst.png",
        "caption": "Figure: test.",
    }
    text = realdata.markdown({"meta": meta, "runs": runs})
    lines = text.splitlines()

    def row(first):
        return next(
            [c.strip() for c in line.strip("|").split("|")]
            for line in lines
            if line.startswith(f"| {first} |")
        )

    # clean: both exact, one Hausdorff within 0.5 %, both Chamfer <= RBF, one fast enough
    assert row("clean")[1:] == ["2", "2 (2)", "1 (2)", "2", "1 of 2", "1"]
    assert row("noisy")[1:] == ["1", "0 (1)", "0 (1)", "0", "0 of 1", "0"]
    assert row("all")[1] == "3"
    assert "2 merged, 1 extra" in text and "b/noisy: ValueError: boom" in text
    assert "![worst runs](realdata/worst.png)" in text
    assert "'il1a\\|' source" in text  # a pipe in a table cell is escaped
    assert "PASS" not in text and "MISS" not in text
    assert realdata.worst_runs(runs, 2) == [1, 2]  # a/noisy (topology), then b/clean


def test_verdict_and_time_tables_count_flagged_misses_and_solves():
    runs = [
        _run("a", "clean", exact=True, hausdorff=0.003, chamfer=1e-4, rbf_chamfer=2e-4, warm_s=0.1),
        _run("a", "noisy", exact=False, hausdorff=0.02, chamfer=3e-4, rbf_chamfer=2e-4, warm_s=0.3),
        _run(
            "b", "clean", exact=False, hausdorff=0.003, chamfer=1e-4, rbf_chamfer=2e-4, warm_s=0.2
        ),
    ]
    runs[1]["jurs"]["status"] = "doubtful"  # the miss flagged; b/clean's miss is silent
    runs[1]["settings"]["held_out"] = [[1e-6, 0.1], [1e-5, 0.2]]

    def cells(lines, first):  # the cells after ``first`` (one or more leading cells)
        line = next(x for x in lines if x.startswith(f"| {first} |"))
        return [c.strip() for c in line.strip("|").split("|")][first.count("|") + 1 :]

    verdicts = realdata.verdict_table(runs)
    assert cells(verdicts, "topology not exact") == ["2", "1"]
    assert cells(verdicts, "Hausdorff over its target") == ["1", "1"]
    assert cells(verdicts, "both met") == ["1", "0"]
    runs.append(
        _run("c", "clean", exact=True, hausdorff=0.003, chamfer=1e-4, rbf_chamfer=2e-4, warm_s=0.9)
    )
    runs[-1]["jurs"].update(finest=[256, 256], active=12000)  # a fit on the adaptive basis
    times = realdata.time_table(runs)
    assert cells(times, "grid | 1") == ["2", "3072", "150 ms", "1"]  # medians of 0.1, 0.2 s
    assert cells(times, "grid | 3") == ["1", "3072", "300 ms", "0"]
    assert cells(times, "adaptive | 1") == ["1", "12000", "900 ms", "0"]


def test_the_figure_shows_one_run_per_case():
    def run(case, variant, exact, hausdorff):
        return _run(
            case,
            variant,
            exact=exact,
            hausdorff=hausdorff,
            chamfer=1e-4,
            rbf_chamfer=2e-4,
            warm_s=0.1,
        )

    runs = [
        run("p", "clean", False, 0.02),
        run("p", "noisy", False, 0.05),
        run("q", "clean", True, 0.001),
        run("q", "noisy", True, 0.002),
        run("r", "noisy", True, 0.009),
    ]
    assert realdata.worst_runs(runs, 8) == [1, 4, 2]  # p/noisy; r/noisy; q/clean
    assert realdata.worst_runs(runs, 2) == [1, 2]  # the worst clean and noisy cases first
