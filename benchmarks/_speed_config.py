"""What ``benchmarks/speed.py`` measures and against which targets: the sizes, settings
and limits its workers run with and its report judges by (shared by the workers, the
report in :mod:`_speed_report` and ``gpu_speed.py``)."""

#: Sweep: points m -> grids (N = M). Fine grids on few points are pruned (with 3m samples
#: far below N*M coefficients the fit is mostly undetermined and says nothing new about
#: speed), and so is part of the rest, to keep the whole run near 30 minutes on 2 cores.
FULL_SWEEP = {
    100: (8, 16, 32),
    1_000: (8, 16, 32, 64),
    10_000: (16, 32, 64, 128),
    100_000: (16, 32, 64, 128, 256),
    1_000_000: (8, 32, 128, 256),  # 8: the only grid where the dense NumPy port fits at 1e6
}
QUICK_SWEEP = {1_000: (16,), 10_000: (128,)}

#: Solvers of the step sweep: (key, label, constructor name and keyword arguments).
STEP_SOLVERS = {
    "iurs": ("IURS (tau=1e-2, lam=1e-3)", "IURS", {"tau": 1e-2, "lam": 1e-3}),
    "ipia": ("IPIA", "IPIA", {}),
    "normal_ipia": ("NormalIPIA", "NormalIPIA", {}),
}
#: The exact solve's objective lambda (sweep, RBF comparison and target).
LSQ_LAM = 1e-4

#: The dense port runs where one 3m x NM float64 matrix is at most this big (B and D, and
#: the temporaries of a step, are each this size).
DENSE_LIMIT_BYTES = 2 * 10**9

#: RBF comparison: points -> a coarser jurs grid, shown for context beside the defaults
#: (which choose their own grid, at most 96 a side).
RBF_GRIDS = {100: 16, 300: 24, 1_000: 32, 2_000: 48, 5_000: 64}
QUICK_RBF_POINTS = (300,)
#: Skip the next RBF size when its fit is predicted (O(m^3) from the last one) to exceed this.
RBF_MAX_PREDICTED_S = 150.0
#: Grid resolution of the zero-set analysis (the same for jurs and the RBF).
ANALYSIS_RESOLUTION = 512
#: Dense samples of the exact Example 1 curve (spacing about 3e-5), the Chamfer reference.
REFERENCE_POINTS = 1_000_000
#: The refined distances (see refined_distances): zero-set samples along the contour, at
#: this many per box diagonal, and reference points projected onto the zero set. Every
#: sample costs the RBF 15 evaluations (3 Newton rounds of a value and a central-difference
#: gradient), 10 s at 5000 points.
REFINED_SAMPLES_PER_DIAGONAL = 2000
REFINED_REFERENCE_SAMPLES = 2000
OFFSET, EPS = 0.1, 0.01

#: The Example-4-size full fit: a 640-point closed shape, 15 x 15, regularised IURS to tol.
#: The paper's Example 4 settings (its lambda, 1.155 s in its Table 2) on the project's
#: stand-in shape, and a smaller lambda on a smooth shape, which converges ten times slower.
EXAMPLE4 = [
    {
        "label": "paper's Example 4: glyph_B, 639 pts",
        "shape": "glyph_B",
        "points": 639,
        "grid": 15,
        "tau": 1e-3,
        "lam": 0.0216,
    },
    {
        "label": "lobes, 640 pts",
        "shape": "lobes",
        "points": 640,
        "grid": 15,
        "tau": 1e-3,
        "lam": 2e-3,
    },
]
EXAMPLE4_TOL, EXAMPLE4_MAX_STEPS = 1e-7, 20_000
#: Fresh processes each Example-4 fit runs in (median cold and warm times over them).
EXAMPLE4_RUNS = 3

#: Targets (seconds, bytes, ratios). The values are requirements, not measurements.
TARGET_IURS_STEP_S = 0.040  # IURS step at 1e6 points / 128 x 128
TARGET_IURS_PEAK_B = 2 * 2**30  # its peak memory (above the post-import baseline)
TARGET_NORMAL_STEP_S = 0.002  # NormalIPIA step at 128 x 128, any m
TARGET_LSQ_S = 1.5  # LeastSquares end to end at 1e6 / 128 x 128, warm
TARGET_EX4_WARM_S, TARGET_EX4_COLD_S = 0.012, 1.5
TARGET_RBF_RATIO, TARGET_RBF_POINTS = 100.0, 5_000
#: "Equal" Chamfer: within this relative margin of the RBF's (the refined distances of
#: refined_distances).
CHAMFER_TOLERANCE = 0.05
TARGET_POINTS, TARGET_GRID = 1_000_000, 128

#: Lower bound on an IURS step's arithmetic: it applies the collocation D (eq. 23) or its
#: transpose at least this many times, 16 multiply-adds a sample each (see bounds_table).
IURS_STEP_PASSES, MACS_PER_PASS = 6, 16
#: Side of the float64 matrix product that measures the machine's multiply-add rate.
CEILING_N = 2000

#: An environment in which glibc's malloc asks for transparent huge pages (glibc >= 2.35,
#: Linux THP in "madvise" or "always" mode). XLA's CPU buffers come from malloc; with 4 KB
#: pages every step of a large problem page-faults its fresh buffers in again. The target
#: measurements are repeated in it (the library itself cannot set it: glibc reads it at
#: process start).
HUGEPAGE_ENV = {"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}

#: The RBF comparison at TARGET_RBF_POINTS also runs jurs with these settings given (the
#: rest automatic): finer grids and smoothings far below the default, the way towards an
#: exact interpolant's accuracy on a smooth curve, but unsafe as defaults
#: (benchmarks/smoothing.py measures why). The target's verdict takes the fastest of them
#: that is as accurate as the RBF.
RBF_GIVEN = [
    {"grid": 64, "smoothing": 1e-10},
    {"grid": 128, "smoothing": 1e-10},
    {"grid": 128, "smoothing": 1e-13},
    {"grid": 256, "smoothing": 1e-13},
]

WORKER_TIMEOUT_S = 900
#: Steps a fit runs beyond its first in the in-fit step measurement (work_fit_steps).
FIT_STEPS = 20
#: The step sweep also times steps in one jitted loop (speed.time_step_loop): as many
#: steps as take about LOOP_S seconds by the standalone step time, within these bounds.
LOOP_S, LOOP_STEPS_MIN, LOOP_STEPS_MAX = 0.05, 5, 200
#: Passes a jitted loop runs when pass_times times one pass over the samples.
PASS_REPEATS = 2000
#: Seconds of warm repeats per timed call (at least 3 repeats, see time_repeated).
STEP_BUDGET_S = 1.5
