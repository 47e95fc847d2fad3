"""The envelope grid of REEP (issue 27, item 7): captures of tests/reference_sim.py and what a cell measures.

A cell is one capture: a sample rate, a lever (f0, Q), a regime (free air, or
steady tapping with the thesis's attractive, attractive/repulsive or repulsive
force, §3.4.3, scaled to the lever) and a measurement noise.  ``run_cell``
simulates it, runs REEP as the command does, and returns what the tests
judge: the bias and scatter of f0′ and Q′, how often the stated ±2σ covers the
truth, and the share of flagged rows.

The truth.  In free air it is the simulated f0 and Q.  In steady tapping it is
twofold: the first-harmonic balance of NOTES.md (ch. 4) by quadrature of the
reference simulator's own force (``first_harmonic``: f0_e and Q_e at each
row's amplitude and separation), and, for the coverage of the stated standard
deviations, REEP's own estimate on the same capture without noise: the
expectation the noise scatters around.  The first differs from the second by
the first-harmonic approximation (a nonlinear force is not a linear spring
and damper) and by the interaction's response to the drive's side lines,
which no statistical uncertainty describes; the grid states that difference
per cell as a tolerance against theory instead.

Tapping captures drive one strong line and side lines scaled to beat the
amplitude by at most 0.5 % (NOTES.md: at Q ≈ 40 unattenuated side lines beat
the envelope by ±17 % and change the interaction) and give REEP the lever's
f0 and Q (the ``f0-q`` route: gain and delay fitted at the drive), as a
scientist with a thermal tune would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afmtool.analyses.reep import run_reep
from afmtool.config import resolve
from afmtool.config.params import ReepParams
from tests import reference_sim as rs
from tests.memory_sink import MemorySink
from tests.test_reep_reference import reference_reader

#: The thesis's §3.4.3 sets at 80,318 Hz (d nm, ω_a², ω_b² 1/s², c_a, c_b 1/s), scaled to each lever.
FORCE_SETS = {
    "attractive": (4.0, 0.31e6**2, 3.03e6**2, 0.042e6, 0.0),
    "mixed": (4.0, 0.1e6**2, 0.303e6**2, 0.0092e6, 0.0),
    "repulsive": (5.0, 0.11e6**2, 0.63e6**2, 0.0042e6, 0.0),
}
#: Hold separation over the free amplitude that puts each set in its regime.
HOLD_SEPARATION = {"attractive": 0.8, "mixed": 0.6, "repulsive": 0.45}
FREE_AMPLITUDE_NM = 20.0
SIDE_OFFSET = 0.075  # side lines at ±7.5 % of f0


def scaled_force(kind: str, f0_hz: float, wall: bool = True) -> rs.PiecewiseLinearForce:
    """The §3.4.3 set for a lever at ``f0_hz``: stiffness with ω0², damping with ω0 (the same dimensionless force).

    ``wall=False`` leaves out the repulsive wall (ω_b², c_b): the attraction alone.
    """
    d, wa2, wb2, ca, cb = FORCE_SETS[kind]
    s = f0_hz / 80318.0
    if not wall:
        wb2 = cb = 0.0
    return rs.PiecewiseLinearForce(d, wa2 * s * s, wb2 * s * s, ca * s, cb * s)


def first_harmonic(amplitude_nm, separation_nm, f0_hz, q, force, drive_hz, n_theta=720):
    """(f_e, Q_e) by the first-harmonic balance of NOTES.md ch. 4, by quadrature of ``force``.

    ωe² = ω0² − (1/πa)∫F(a cosθ, −aω sinθ) cosθ dθ and
    ωe/Qe = ω0/Q + (1/(πaω))∫F(a cosθ, −aω sinθ) sinθ dθ, with ω the drive.
    """
    a = np.asarray(amplitude_nm, dtype=float)[:, None]
    l = np.asarray(separation_nm, dtype=float)[:, None]
    theta = (np.arange(n_theta) + 0.5) * (2 * np.pi / n_theta)
    w = 2 * np.pi * drive_hz
    f = force(a * np.cos(theta), -a * w * np.sin(theta), l)
    step = 2 * np.pi / n_theta
    w0 = 2 * np.pi * f0_hz
    we = np.sqrt(w0 * w0 - (f @ np.cos(theta)) * step / (np.pi * a[:, 0]))
    damping = w0 / q + (f @ np.sin(theta)) * step / (np.pi * a[:, 0] * w)
    return we / (2 * np.pi), we / damping


@dataclass(frozen=True)
class Cell:
    """One capture of the grid; the tolerances it is judged by are written beside it (tests/test_reep_envelope.py)."""

    fs: float
    f0: float
    q: float
    regime: str  # "free", "attractive", "mixed", "repulsive"
    noise_nm: float
    seed: int = 1
    #: Free amplitude A0, nm (40 nm for repulsive tapping at Q ≥ 400: at 20 nm the lever stays in the attractive
    #: branch at every separation with A ≥ 0.45 A0).
    free_amplitude_nm: float = FREE_AMPLITUDE_NM
    #: Hold separation over A0 (None: the regime's, HOLD_SEPARATION).  Attractive tapping at Q 20 holds at 0.9:
    #: at 0.8 the weakly damped amplitude barely drops and the tip grazes the wall (0.4 nm into it).
    hold_fraction: float | None = None
    #: Tolerances: |mean f0′ − truth| (Hz), |mean Q′/truth − 1|, flagged share, ±2σ coverage band.
    f0_tol_hz: float = 2.0
    q_tol: float = 0.02
    flagged_max: float = 0.10
    coverage: tuple[float, float] = (0.90, 0.99)
    extra: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.regime}-{self.fs / 1e6:g}MHz-{self.f0 / 1e3:g}kHz-Q{self.q:g}-{self.noise_nm:g}nm"


def _lever_time_constant(f0: float, q: float) -> float:
    """The amplitude's decay time Q/(π f0), s."""
    return q / (math.pi * f0)


def free_air_capture(cell: Cell, duration_s: float | None = None) -> rs.Capture:
    gain = 1.0
    duration = duration_s or 0.06
    drive = rs.three_sine(cell.f0, SIDE_OFFSET * cell.f0, cell.free_amplitude_nm / (gain * cell.q), 0.5)
    return rs.simulate(f0_hz=cell.f0, q=cell.q, gain_nm_per_v=gain, sample_rate_hz=cell.fs, duration_s=duration,
                       drive=drive, noise_nm=cell.noise_nm, seed=cell.seed)


def tapping_capture(cell: Cell) -> tuple[rs.Capture, float]:
    """Free air, a ramp over three lever time constants to the hold separation, then a hold; and the hold's start, s."""
    tau = _lever_time_constant(cell.f0, cell.q)
    free_s = 0.01
    ramp_s = max(3 * tau, 0.005)
    settle_s = 8 * tau + 0.004  # the amplitude settles, then REEP's window (400 µs) follows
    hold_s = settle_s + 0.03
    top = cell.free_amplitude_nm + FORCE_SETS[cell.regime][0] + 5.0
    low = (cell.hold_fraction or HOLD_SEPARATION[cell.regime]) * cell.free_amplitude_nm

    def separation(t):
        t = np.asarray(t, dtype=float)
        fraction = np.clip((t - free_s) / ramp_s, 0.0, 1.0)
        return top - (top - low) * fraction

    # side lines beating the amplitude by at most 0.5 % (module docstring)
    side = min(0.25, 0.005 * SIDE_OFFSET * cell.q)
    drive = rs.three_sine(cell.f0, SIDE_OFFSET * cell.f0, cell.free_amplitude_nm / cell.q, side)
    cap = rs.simulate(f0_hz=cell.f0, q=cell.q, gain_nm_per_v=1.0, sample_rate_hz=cell.fs,
                      duration_s=free_s + ramp_s + hold_s, drive=drive, noise_nm=cell.noise_nm, seed=cell.seed,
                      force=scaled_force(cell.regime, cell.f0), separation_nm=separation, free_air_s=free_s)
    return cap, free_s + ramp_s + settle_s


def run(cap: rs.Capture, **overrides):
    """REEP on a capture as ``afmtool reep`` runs it: (result, columns)."""
    columns = MemorySink()
    result = run_reep(reference_reader(cap), resolve(ReepParams, overrides), columns)
    return result, columns


def without_noise(cap: rs.Capture) -> rs.Capture:
    """The same capture with the clean deflection."""
    channels = dict(cap.channels, deflection=cap.truth["deflection_clean"])
    return rs.Capture(cap.sample_rate_hz, channels, cap.units, cap.truth, cap.metadata)


def coverage(values, truth, std) -> float:
    """Share of rows within ±2 std of the truth."""
    return float(np.mean(np.abs(np.asarray(values) - truth) <= 2.0 * np.asarray(std)))


def run_cell(cell: Cell) -> dict:
    """Simulate and measure one cell (module docstring); every number the tests and the notes table use."""
    if cell.regime == "free":
        return _free_cell(cell)
    return _tapping_cell(cell)


def _free_cell(cell: Cell) -> dict:
    cap = free_air_capture(cell)
    result, columns = run(cap)
    t = columns["t"]
    rows = t > 0.015
    f0, q = columns["f0_hz"][rows], columns["q"][rows]
    good = columns["flag"][rows] == 0
    return {
        "cell": cell.name, "rate_reduction": result.results.estimator.rate_reduction,
        "f0_bias_hz": float(np.mean(f0[good]) - cell.f0), "q_bias": float(np.mean(q[good]) / cell.q - 1.0),
        "f0_scatter_hz": float(np.std(f0[good])), "q_scatter": float(np.std(q[good]) / cell.q),
        "f0_std_hz": float(np.median(columns["f0_std_hz"][rows][good])),
        "q_std": float(np.median(columns["q_std"][rows][good]) / cell.q),
        "f0_coverage": coverage(f0[good], cell.f0, columns["f0_std_hz"][rows][good]),
        "q_coverage": coverage(q[good], cell.q, columns["q_std"][rows][good]),
        "flagged": float(np.mean(~good)),
    }


def _tapping_cell(cell: Cell) -> dict:
    cap, hold_from = tapping_capture(cell)
    route = {"f0_hz": cell.f0, "q": cell.q}
    result, columns = run(cap, **route)
    _, clean = run(without_noise(cap), **route)
    fs = cell.fs
    t = columns["t"]
    index = np.round(t * fs).astype(int)
    free_amplitude = result.results.validity.free_air_levels.amplitude
    separation = cap.truth["separation_nm"][index]
    # a row taps when the tip reached the force's range in the period before it
    period = int(round(fs / cell.f0)) + 1
    recent = _touched(cap, index, period)
    steady = (t >= hold_from) & (columns["amplitude"] >= 0.45 * free_amplitude) & recent
    clean_min = _min_separation(cap, index[steady], period)
    drive_hz = result.results.drive_frequency_hz
    f0_e, q_e = first_harmonic(columns["amplitude"][steady], separation[steady], cell.f0, cell.q,
                               scaled_force(cell.regime, cell.f0), drive_hz)
    # the attraction's and the wall's shares of the theory's shift: its first-harmonic error scales with
    # each part, not with their sum (in mixed tapping they cancel)
    f0_a, q_a = first_harmonic(columns["amplitude"][steady], separation[steady], cell.f0, cell.q,
                               scaled_force(cell.regime, cell.f0, wall=False), drive_hz)
    good = columns["flag"][steady] == 0
    f0, q = columns["f0_hz"][steady][good], columns["q"][steady][good]
    f0_std, q_std = columns["f0_std_hz"][steady][good], columns["q_std"][steady][good]
    f0_clean, q_clean = clean["f0_hz"][steady][good], clean["q"][steady][good]
    return {
        "cell": cell.name, "rate_reduction": result.results.estimator.rate_reduction,
        "steady_rows": int(np.count_nonzero(steady)),
        "amplitude_share": float(np.mean(columns["amplitude"][steady]) / free_amplitude),
        "min_separation_nm": float(np.median(clean_min)),
        "f0_shift_hz": float(np.mean(f0_e) - cell.f0),
        "f0_shift_scale_hz": float(abs(np.mean(f0_a) - cell.f0) + abs(np.mean(f0_e - f0_a))),
        "q_shift": float(np.mean(q_e) / cell.q - 1.0),
        "q_shift_scale": float(abs(np.mean(q_a) / cell.q - 1.0) + abs(np.mean(q_e - q_a)) / cell.q),
        "f0_bias_hz": float(np.mean(f0 - f0_e[good])), "q_bias": float(np.mean(q / q_e[good]) - 1.0),
        "f0_scatter_hz": float(np.std(f0 - f0_clean)), "q_scatter": float(np.std(q / q_clean - 1.0)),
        "f0_std_hz": float(np.median(f0_std)), "q_std": float(np.median(q_std / q_clean)),
        "f0_coverage": coverage(f0, f0_clean, f0_std), "q_coverage": coverage(q, q_clean, q_std),
        "f0_theory_coverage": coverage(f0, f0_e[good], f0_std),
        "flagged": float(np.mean(~good)),
    }


def _touched(cap: rs.Capture, index: np.ndarray, period: int) -> np.ndarray:
    """Whether the tip reached the force's range in the period before each row."""
    contact = np.concatenate(([0], np.cumsum(cap.truth["contact"], dtype=np.int64)))
    return contact[index + 1] - contact[np.maximum(index + 1 - period, 0)] > 0


def _min_separation(cap: rs.Capture, index: np.ndarray, period: int) -> np.ndarray:
    """The least tip–sample separation p + l over the period before each row (noise-free), nm."""
    ts = cap.truth["deflection_clean"] + cap.truth["separation_nm"]
    return np.array([ts[max(i - period, 0): i + 1].min() for i in index])
