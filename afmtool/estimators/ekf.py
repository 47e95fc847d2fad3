"""Continuous-discrete extended Kalman filter of the electrostatically actuated lever (ch. 7).

Model (eqs. 7.11-7.13), state x = [p, ṗ] in **nm and nm/s**, measurement y
the deflection in nm::

    ẋ1 = x2
    ẋ2 = −ω0²x1 − (ω0/Q)x2 + u(x1, V) + η,     u = −c·V²/(ℓ0 + x1)²,   c = ω0²·K_esf/k · 1e27
    y  = x1 + ν

The force is that of :mod:`afmtool.models.electrostatic` (attractive,
F_esf = −K_esf·V²/ℓ_s², **no ½**, K_esf in F·m, ℓ in m) per unit mass,
F/m = (ω0²/k)·F, converted to nm/s² with ℓ in nm: c·V²/ℓ_nm² = (ω0²/k)·
K_esf·V²/(ℓ_nm·1e-9)²·1e9.  The filter models the nominal sample (d = 0 in
eq. 7.11, z = 0 here); topography and surface-potential changes are what
its innovation reveals (eq. 7.19).  The separation is clipped at the tip
height t_h as in eq. 6.4.

Prediction (between samples t_{n−1} and t_n, T = 1/f_s)
-------------------------------------------------------
The linear part is discretised exactly, Φ = e^{AT} with A = [[0, 1],
[−ω0², −ω0/Q]].  Over the step the force is u(s) = g·V(s)² with
g = −c/ℓ_mid², the gap taken at the mid-step prediction
ℓ_mid = ℓ0 + x̂1 + x̂2·T/2, and V² the causal quartic through the samples
V²(n−4) … V²(n) (nodes s = −3T … T).  Then, exactly for that u,

.. math::

    x^-(n) = \\Phi\\hat x(n-1) + g\\,w(n),\\qquad
    w(n) = \\sum_{j} \\Gamma_j V^2(n - 1 + j),\\quad j = -3 \\dots 1,

with Γ_j = ∫₀ᵀ e^{A(T−s)}B L_j(s/T) ds for the Lagrange basis L_j and
B = [0, 1]ᵀ (moments of e^{A(T−s)}B from one augmented matrix exponential,
:func:`interpolation_weights`).  The V² samples carry the actuation at
10-20 samples per period; held constant (zero-order hold) or linear over
the step they leave a deterministic residual of 0.1 nm at the thesis's
settings, a quadratic 0.02 nm, the quartic below 0.01 nm (the remainder is
the mid-step gap), far under the thermal (0.17 nm) and optical (0.05 nm)
noise; ``tests/test_decode.py`` checks it on the simulator.

Covariance (eq. 7.17 linearisation): F = Φ + w·∇gᵀ with ∇g = dg·[1, T/2],
dg = ∂g/∂ℓ = 2c/ℓ³, and P⁻ = F P Fᵀ + Q_d, with Q_d the exact
discretisation (Van Loan) of white acceleration noise η of one-sided PSD
S_η = (ω0²/k)²·S_F (S_F the force-noise PSD, N²/Hz) entering through B.
dg is evaluated at the mid-step gap of the *prior* x⁻(n−1) instead of the
posterior x̂(n−1).  They differ by K·ε(n−1), a relative change of about
1e-4 in dg (a few 0.1 nm in a 1 µm gap), which does not show in the gain;
it takes the division 1/ℓ off the P → K → x̂ → P chain and makes the
kernel about 1.4× faster.

Update (scalar measurement, H = C = [1, 0])::

    ε = y − x1⁻                      (the innovation, e1 of eq. 7.16)
    S = P⁻00 + R
    K = [P⁻00, P⁻01]/S
    x̂ = x⁻ + K ε
    P = (I − KH) P⁻ (I − KH)ᵀ + K R Kᵀ   (Joseph form)

P is carried as three scalars (P00, P01, P11), so it is symmetric by
construction.  The Joseph form keeps it positive semi-definite in floating
point when the gain is close to 1 (P⁻00 ≫ R: a fast filter on a quiet
sensor), where the short form (I − KH)P⁻ subtracts nearly equal numbers.

Outputs per sample: the innovation ε (nm) and its running mean over
``mean_window`` samples (one actuation period cancels the lines at the
actuation frequency and its harmonics; the "mean of the error signal" of
§7.7).  The kernel also sums ε² and the normalised innovation ε²/S after
``stats_from`` samples, for the ℓ0 search (§7.4) and noise tuning.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError
from afmtool.jit import JIT_OPTIONS
from afmtool.models.electrostatic import ElectrostaticParams, LeverVoltages

__all__ = [
    "BOLTZMANN_J_PER_K",
    "EkfModel",
    "EkfDesign",
    "EkfState",
    "EkfBlock",
    "EkfStep",
    "InnovationStats",
    "discretise",
    "ekf_update",
    "ekf_run",
    "ekf_from_prior",
    "ekf_forgetting_samples",
    "InnovationSums",
    "force_per_mass_constant",
    "interpolation_weights",
    "thermal_force_asd",
    "V2_NODES",
]

#: Boltzmann constant k_B, J/K (exact, SI 2019).
BOLTZMANN_J_PER_K = 1.380649e-23

#: Initial standard deviation of the position estimate, nm (x̂(0) = 0, eq. 7.14).
DEFAULT_P0_NM = 1.0e3

#: The running-mean sum is recomputed from its ring every this many windows
#: (aligned to the stream, not to chunks), so rounding cannot accumulate.
_RESYNC_WINDOWS = 4096

# Slots of the coefficient vector (read-only in the kernel).
(
    _PHI00, _PHI01, _PHI10, _PHI11,
    _GA0, _GA1, _GB0, _GB1, _GC0, _GC1, _GD0, _GD1, _GE0, _GE1,
    _QD00, _QD01, _QD11,
    _R, _C, _L0, _TH, _HALF_T, _P0_POS, _P0_VEL,
    _COEF_LEN,
) = range(25)

#: Interpolation nodes of V² over the step from t_{n−1} (s = 0) to t_n (s = T), in units of T:
#: the samples n−4 … n.  One-sided (causal) quartic: its error is O((ωT)⁵).
V2_NODES = (-3, -2, -1, 0, 1)

# Slots of the carried state vector (read at kernel entry, written at exit).
(
    _X1, _X2, _P00, _P01, _P11,
    _V2_1, _V2_2, _V2_3, _V2_4, _DG,
    _N, _SUM, _POS, _FILLED,
    _STATS_FROM, _SUM_E2, _SUM_NIS, _COUNT,
    _STATE_LEN,
) = range(19)


def force_per_mass_constant(f0_hz: float, spring_constant_n_per_m: float, k_esf_f_m: float) -> float:
    """c = ω0²·K_esf/k·1e27, so that F_esf/m = −c·V²/ℓ² in nm/s² with ℓ in nm (eq. 7.11)."""
    w0 = 2.0 * math.pi * f0_hz
    return w0 * w0 * k_esf_f_m / spring_constant_n_per_m * 1e27


def thermal_force_asd(spring_constant_n_per_m: float, f0_hz: float, q: float, temperature_k: float) -> float:
    """One-sided thermal force-noise ASD √(4k_B·T·k/(ω0·Q)), N/√Hz (damping c = k/(ω0Q))."""
    return math.sqrt(4.0 * BOLTZMANN_J_PER_K * temperature_k * spring_constant_n_per_m / (2 * math.pi * f0_hz * q))


def _check_positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")


def _check_nonneg(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value >= 0):
        raise ConfigError(f"{name}={value!r} must be a finite number >= 0")


@dataclass(frozen=True)
class EkfModel:
    """The nominal plant of eqs. 7.11-7.13 and the noise the filter assumes.

    Parameters
    ----------
    f0_hz : float
        Free resonant frequency f0, Hz (§7.2.1).
    q : float
        Quality factor Q.
    electrostatic : ElectrostaticParams
        k, K_esf (no ½), ℓ0, t_h (α_R only matters when V is built from
        V_R and V_sub, which the caller does).
    process_noise_n_per_rthz : float
        One-sided ASD of the white force noise, N/√Hz (thermal:
        :func:`thermal_force_asd`); ≥ 0.
    measurement_noise_nm : float
        Rms white measurement noise per sample, nm; > 0.
    """

    f0_hz: float
    q: float
    electrostatic: ElectrostaticParams
    process_noise_n_per_rthz: float
    measurement_noise_nm: float

    def __post_init__(self) -> None:
        _check_positive("f0_hz", self.f0_hz)
        _check_positive("q", self.q)
        _check_nonneg("process_noise_n_per_rthz", self.process_noise_n_per_rthz)
        _check_positive("measurement_noise_nm", self.measurement_noise_nm)

    def with_l0(self, l0_m: float) -> EkfModel:
        """The same model with ℓ0 = ``l0_m`` (m)."""
        return replace(self, electrostatic=replace(self.electrostatic, l0_m=float(l0_m)))

    def with_noise(self, process_noise_n_per_rthz: float, measurement_noise_nm: float) -> EkfModel:
        return replace(
            self,
            process_noise_n_per_rthz=float(process_noise_n_per_rthz),
            measurement_noise_nm=float(measurement_noise_nm),
        )

    @property
    def acceleration_psd_nm2_s4_hz(self) -> float:
        """S_η = (ω0²/k)²·S_F·1e18, one-sided, nm²/s⁴/Hz."""
        w0 = 2.0 * math.pi * self.f0_hz
        gain = w0 * w0 / self.electrostatic.spring_constant_n_per_m
        return (gain * self.process_noise_n_per_rthz) ** 2 * 1e18


@dataclass(frozen=True)
class EkfDesign:
    """An :class:`EkfModel` discretised for one sample rate (module docstring).

    ``coef`` holds Φ, Γ_{−1}, Γ_0, Γ_1, Q_d, R, c, ℓ0 (nm), t_h (nm), T/2 and
    the initial standard deviations, read-only.  Build it with
    :func:`discretise`.
    """

    model: EkfModel
    sample_rate_hz: float
    mean_window: int
    coef: np.ndarray

    def with_l0(self, l0_m: float) -> EkfDesign:
        """The same design with ℓ0 = ``l0_m`` (m): only the gap constant changes."""
        model = self.model.with_l0(l0_m)
        coef = self.coef.copy()
        coef[_L0] = model.electrostatic.l0_m * 1e9
        coef.flags.writeable = False
        return EkfDesign(model, self.sample_rate_hz, self.mean_window, coef)

    def with_noise(self, process_noise_n_per_rthz: float, measurement_noise_nm: float) -> EkfDesign:
        """The same design with other noise levels: Q_d and R change, Φ and Γ do not."""
        model = self.model.with_noise(process_noise_n_per_rthz, measurement_noise_nm)
        coef = self.coef.copy()
        _set_noise(coef, model, self.sample_rate_hz)
        coef.flags.writeable = False
        return EkfDesign(model, self.sample_rate_hz, self.mean_window, coef)

    @property
    def phi(self) -> np.ndarray:
        """Φ = e^{AT}, 2×2."""
        c = self.coef
        return np.array([[c[_PHI00], c[_PHI01]], [c[_PHI10], c[_PHI11]]])

    @property
    def gammas(self) -> np.ndarray:
        """Γ_j for the V² samples n−4 … n (rows), s² and s (per nm/s² of force)."""
        return self.coef[_GA0 : _GE1 + 1].reshape(5, 2).copy()

    @property
    def initial_std(self) -> tuple[float, float]:
        """Standard deviations of x̂(0) = 0: (nm, nm/s)."""
        return float(self.coef[_P0_POS]), float(self.coef[_P0_VEL])

    @property
    def process_covariance(self) -> np.ndarray:
        """Q_d, nm² and (nm/s)², 2×2."""
        c = self.coef
        return np.array([[c[_QD00], c[_QD01]], [c[_QD01], c[_QD11]]])


@functools.lru_cache(maxsize=64)
def _expm_of(matrix: bytes, size: int) -> np.ndarray:
    from scipy.linalg import expm

    e = expm(np.frombuffer(matrix).reshape(size, size))
    e.flags.writeable = False
    return e


def _expm(m: np.ndarray) -> np.ndarray:
    """e^M (read-only), remembered: the ℓ0 and noise searches discretise the same plant dozens of times."""
    return _expm_of(np.ascontiguousarray(m, dtype=np.float64).tobytes(), m.shape[0])


def _moments(a: np.ndarray, period: float, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Φ = e^{AT} and the moments M_k = ∫₀ᵀ e^{A(T−s)}B s^k ds, k = 0 … order (rows).

    One augmented matrix exponential: the system ż = Mz with a chain of
    integrators behind B (ż2 = z3, …, z_{order+2} constant) started at the
    unit vector of z_{k+2} feeds B with s^k/k!, so e^{MT}[:2, 2 + k] = M_k/k!.
    """
    size = 3 + order
    m = np.zeros((size, size))
    m[:2, :2] = a
    m[1, 2] = 1.0  # B = [0, 1]ᵀ
    for k in range(2, size - 1):
        m[k, k + 1] = 1.0
    e = _expm(m * period)
    moments = np.array([e[:2, 2 + k] * math.factorial(k) for k in range(order + 1)])
    return e[:2, :2], moments


def interpolation_weights(a: np.ndarray, period: float, nodes=V2_NODES) -> np.ndarray:
    """Γ_j = ∫₀ᵀ e^{A(T−s)}B L_j(s/T) ds for the Lagrange basis L_j on ``nodes`` (rows j).

    Exact response of ẋ = Ax + Bu over one step to the u that interpolates
    u(node·T) = u_j: x(T) = Φx(0) + Σ_j Γ_j u_j.
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    _, moments = _moments(a, period, len(nodes) - 1)
    weights = np.empty((len(nodes), 2))
    for j, node in enumerate(nodes):
        others = np.delete(nodes, j)
        # L_j(σ) = Π (σ − n_m)/(n_j − n_m) = Σ_k c_k σ^k, σ = s/T
        coeffs = np.poly(others)[::-1] / np.prod(node - others)
        weights[j] = sum(c_k * moments[k] / period**k for k, c_k in enumerate(coeffs))
    return weights


def _van_loan(a: np.ndarray, qc: float, period: float) -> np.ndarray:
    """Q_d = ∫₀ᵀ e^{Aτ}B q_c Bᵀ e^{Aᵀτ} dτ (Van Loan, 1978)."""
    g = np.zeros((2, 2))
    g[1, 1] = qc
    m = np.zeros((4, 4))
    m[:2, :2] = -a
    m[:2, 2:] = g
    m[2:, 2:] = a.T
    e = _expm(m * period)
    qd = e[2:, 2:].T @ e[:2, 2:]
    return 0.5 * (qd + qd.T)


def _state_matrix(model: EkfModel) -> np.ndarray:
    """A = [[0, 1], [−ω0², −ω0/Q]] (eq. 7.13), 1/s and 1/s²."""
    w0 = 2.0 * math.pi * model.f0_hz
    return np.array([[0.0, 1.0], [-w0 * w0, -w0 / model.q]])


def _set_noise(coef: np.ndarray, model: EkfModel, sample_rate_hz: float) -> None:
    """Q_d (Van Loan, two-sided density S_η/2) and R = σ_ν² into ``coef``."""
    qd = _van_loan(_state_matrix(model), 0.5 * model.acceleration_psd_nm2_s4_hz, 1.0 / sample_rate_hz)
    coef[_QD00], coef[_QD01], coef[_QD11] = qd[0, 0], qd[0, 1], qd[1, 1]
    coef[_R] = model.measurement_noise_nm**2


def discretise(
    model: EkfModel, sample_rate_hz: float, mean_window: int = 1, *, p0_nm: float = DEFAULT_P0_NM
) -> EkfDesign:
    """Discretise the EKF of eqs. 7.12-7.15 for ``sample_rate_hz``.

    Parameters
    ----------
    model : EkfModel
        Plant and noise.
    sample_rate_hz : float
        f_s = 1/T, Hz; f0 must be below f_s/2.
    mean_window : int, optional
        Samples in the running mean of the innovation, ≥ 1.
    p0_nm : float, optional
        Standard deviation of x̂1(0) = 0, nm; that of x̂2(0) = 0 is
        2π·f0·p0_nm (nm/s).

    Returns
    -------
    EkfDesign
    """
    _check_positive("sample_rate_hz", sample_rate_hz)
    _check_positive("p0_nm", p0_nm)
    if model.f0_hz >= sample_rate_hz / 2:
        raise ConfigError(f"f0_hz={model.f0_hz!r} must be below sample_rate_hz/2 = {sample_rate_hz / 2:g}")
    if not (isinstance(mean_window, (int, np.integer)) and mean_window >= 1):
        raise ConfigError(f"mean_window={mean_window!r} must be an integer >= 1")
    period = 1.0 / sample_rate_hz
    w0 = 2.0 * math.pi * model.f0_hz
    a = _state_matrix(model)
    phi = _moments(a, period, 0)[0]
    gammas = interpolation_weights(a, period)
    es = model.electrostatic
    coef = np.empty(_COEF_LEN)
    coef[_PHI00], coef[_PHI01], coef[_PHI10], coef[_PHI11] = phi.ravel()
    coef[_GA0 : _GE1 + 1] = gammas.ravel()
    _set_noise(coef, model, sample_rate_hz)
    coef[_C] = force_per_mass_constant(model.f0_hz, es.spring_constant_n_per_m, es.k_esf_f_m)
    coef[_L0] = es.l0_m * 1e9
    coef[_TH] = es.tip_height_m * 1e9
    coef[_HALF_T] = 0.5 * period
    coef[_P0_POS] = p0_nm
    coef[_P0_VEL] = w0 * p0_nm
    coef.flags.writeable = False
    return EkfDesign(model, float(sample_rate_hz), int(mean_window), coef)


# --------------------------------------------------------------------------- kernel


@njit(**JIT_OPTIONS)
def _ekf_kernel(y, volts_a, volts_b, alpha, beta, coef, state, ring, out_e, out_mean):  # noqa: PLR0915 - numba kernel: one scalar recursion
    """Run the EKF over one chunk; ``state`` and ``ring`` are updated in place.

    The voltage is V(n) = alpha·volts_a(n) − beta·volts_b(n): α_R, V_R, 1,
    V_sub for eq. 6.3, or 1, V, 0, V for a voltage given directly (exactly V).

    One iteration per sample: predict from t_{n−1} (skipped for the first
    sample of the stream, which starts from x̂(0) = 0, P(0) = diag(σ1², σ2²)),
    update with y(n), push ε(n) into the running mean.
    """
    phi00 = coef[_PHI00]
    phi01 = coef[_PHI01]
    phi10 = coef[_PHI10]
    phi11 = coef[_PHI11]
    ga0 = coef[_GA0]
    ga1 = coef[_GA1]
    gb0 = coef[_GB0]
    gb1 = coef[_GB1]
    gc0 = coef[_GC0]
    gc1 = coef[_GC1]
    gd0 = coef[_GD0]
    gd1 = coef[_GD1]
    ge0 = coef[_GE0]
    ge1 = coef[_GE1]
    qd00 = coef[_QD00]
    qd01 = coef[_QD01]
    qd11 = coef[_QD11]
    r = coef[_R]
    c = coef[_C]
    l0 = coef[_L0]
    th = coef[_TH]
    half_t = coef[_HALF_T]

    x1 = state[_X1]
    x2 = state[_X2]
    p00 = state[_P00]
    p01 = state[_P01]
    p11 = state[_P11]
    v2_1 = state[_V2_1]
    v2_2 = state[_V2_2]
    v2_3 = state[_V2_3]
    v2_4 = state[_V2_4]
    dg = state[_DG]
    n = int(state[_N])
    total = state[_SUM]
    pos = int(state[_POS])
    filled = int(state[_FILLED])
    stats_from = state[_STATS_FROM]
    sum_e2 = state[_SUM_E2]
    sum_nis = state[_SUM_NIS]
    count = state[_COUNT]
    window = ring.shape[0]
    resync = window * _RESYNC_WINDOWS
    # countdown to the next resynchronisation at n ≡ 0 (mod resync); no division per sample
    until_resync = resync - n % resync

    for i in range(y.shape[0]):
        volts = alpha * volts_a[i] - beta * volts_b[i]
        v2 = volts * volts
        if n == 0:
            # x̂⁻(0) = 0, P⁻(0) = diag(σ1², σ2²) (eq. 7.14); V² before the stream = V²(0)
            xp1 = 0.0
            xp2 = 0.0
            pp00 = coef[_P0_POS] * coef[_P0_POS]
            pp01 = 0.0
            pp11 = coef[_P0_VEL] * coef[_P0_VEL]
            v2_1 = v2
            v2_2 = v2
            v2_3 = v2
            v2_4 = v2
        else:
            # ℓ_mid = ℓ0 + x̂1 + x̂2·T/2, clipped at t_h (eq. 6.4)
            gap = l0 + x1 + half_t * x2
            if gap < th:
                gap = th
            # g = −c/ℓ_mid²
            inv_gap = 1.0 / gap
            g = -c * inv_gap * inv_gap
            # w = Σ_j Γ_j V²(n − 1 + node_j), nodes −3 … 1
            w0 = ga0 * v2_4 + gb0 * v2_3 + gc0 * v2_2 + gd0 * v2_1 + ge0 * v2
            w1 = ga1 * v2_4 + gb1 * v2_3 + gc1 * v2_2 + gd1 * v2_1 + ge1 * v2
            # x⁻ = Φ x̂ + g·w
            xp1 = phi00 * x1 + phi01 * x2 + g * w0
            xp2 = phi10 * x1 + phi11 * x2 + g * w1
            # F = Φ + w ∇gᵀ, ∇g = dg·[1, T/2], dg = 2c/ℓ³ at the prior's gap (module docstring, Covariance)
            dg_v = dg * half_t
            f00 = phi00 + w0 * dg
            f01 = phi01 + w0 * dg_v
            f10 = phi10 + w1 * dg
            f11 = phi11 + w1 * dg_v
            # M = F P
            m00 = f00 * p00 + f01 * p01
            m01 = f00 * p01 + f01 * p11
            m10 = f10 * p00 + f11 * p01
            m11 = f10 * p01 + f11 * p11
            # P⁻ = M Fᵀ + Q_d, upper triangle only (symmetric by construction)
            pp00 = m00 * f00 + m01 * f01 + qd00
            pp01 = m00 * f10 + m01 * f11 + qd01
            pp11 = m10 * f10 + m11 * f11 + qd11
            v2_4 = v2_3
            v2_3 = v2_2
            v2_2 = v2_1
            v2_1 = v2
        # dg = ∂g/∂ℓ = 2c/ℓ³ at the prior's mid-step gap ℓ0 + x1⁻ + x2⁻·T/2, for F of the next step
        lin_gap = l0 + xp1 + half_t * xp2
        if lin_gap > th:
            inv_lin = 1.0 / lin_gap
            dg = 2.0 * c * inv_lin * inv_lin * inv_lin
        else:
            dg = 0.0
        # ε = y − C x⁻
        e = y[i] - xp1
        # S = C P⁻ Cᵀ + R
        inv_s = 1.0 / (pp00 + r)
        # K = P⁻ Cᵀ S⁻¹
        k0 = pp00 * inv_s
        k1 = pp01 * inv_s
        # x̂ = x⁻ + K ε
        x1 = xp1 + k0 * e
        x2 = xp2 + k1 * e
        # P = (I − KC) P⁻ (I − KC)ᵀ + K R Kᵀ (Joseph form, three scalars)
        a = 1.0 - k0
        p00 = a * a * pp00 + k0 * k0 * r
        p01 = a * (pp01 - k1 * pp00) + k0 * k1 * r
        p11 = k1 * k1 * pp00 - 2.0 * k1 * pp01 + pp11 + k1 * k1 * r
        out_e[i] = e
        if n >= stats_from:
            sum_e2 += e * e
            sum_nis += e * e * inv_s
            count += 1.0
        # running mean of ε over the last `window` samples
        if filled < window:
            filled += 1
        else:
            total -= ring[pos]
        ring[pos] = e
        total += e
        pos += 1
        if pos == window:
            pos = 0
        n += 1
        until_resync -= 1
        if until_resync == 0:
            until_resync = resync
            total = 0.0
            for j in range(window):
                total += ring[j]
        out_mean[i] = total / filled

    state[_X1] = x1
    state[_X2] = x2
    state[_P00] = p00
    state[_P01] = p01
    state[_P11] = p11
    state[_V2_1] = v2_1
    state[_V2_2] = v2_2
    state[_V2_3] = v2_3
    state[_V2_4] = v2_4
    state[_DG] = dg
    state[_N] = n
    state[_SUM] = total
    state[_POS] = pos
    state[_FILLED] = filled
    state[_SUM_E2] = sum_e2
    state[_SUM_NIS] = sum_nis
    state[_COUNT] = count


# --------------------------------------------------------------------------- wrappers


class InnovationStats(NamedTuple):
    """Innovation statistics accumulated after ``stats_from`` samples."""

    rms_nm: float  #: √mean(ε²), nm (NaN if no sample counted)
    mean_nis: float  #: mean of ε²/S, the normalised innovation squared (1 for a consistent filter)
    count: int  #: samples counted


@dataclass(frozen=True)
class EkfState:
    """Everything the EKF carries from one sample to the next (immutable).

    ``vector`` holds x̂ (nm, nm/s), P (three scalars), V² of the two previous
    samples, the sample count, the running-mean sum and ring position, and
    the statistics sums; ``ring`` the last ``mean_window`` innovations.
    Build the first state with :meth:`initial`.
    """

    vector: np.ndarray
    ring: np.ndarray

    @classmethod
    def initial(cls, design: EkfDesign, *, stats_from: int = 0) -> EkfState:
        """The state before the first sample; statistics count samples n ≥ ``stats_from``."""
        if not (isinstance(stats_from, (int, np.integer)) and stats_from >= 0):
            raise ConfigError(f"stats_from={stats_from!r} must be an integer >= 0")
        vector = np.zeros(_STATE_LEN)
        vector[_STATS_FROM] = stats_from
        return cls(vector, np.zeros(design.mean_window))

    @property
    def samples_seen(self) -> int:
        return int(self.vector[_N])

    @property
    def estimate(self) -> tuple[float, float]:
        """x̂ = (p̂ in nm, ṗ̂ in nm/s) after the last sample."""
        return float(self.vector[_X1]), float(self.vector[_X2])

    @property
    def covariance(self) -> np.ndarray:
        """P after the last sample, 2×2 (nm², nm²/s, nm²/s²)."""
        v = self.vector
        return np.array([[v[_P00], v[_P01]], [v[_P01], v[_P11]]])

    def stats(self) -> InnovationStats:
        """ε statistics over the samples counted so far."""
        count = int(self.vector[_COUNT])
        if count == 0:
            return InnovationStats(math.nan, math.nan, 0)
        return InnovationStats(
            math.sqrt(self.vector[_SUM_E2] / count), float(self.vector[_SUM_NIS] / count), count
        )


class EkfBlock(NamedTuple):
    """One chunk of EKF output, one value per input sample."""

    innovation_nm: np.ndarray  #: ε(n) = y(n) − x̂1⁻(n), nm
    mean_nm: np.ndarray  #: running mean of ε over ``mean_window`` samples, nm


class EkfStep(NamedTuple):
    """Output of :func:`ekf_update`: the chunk's block and the state for the next chunk."""

    block: EkfBlock
    state: EkfState


def ekf_update(design: EkfDesign, state: EkfState, deflection_nm, voltage_v: np.ndarray | LeverVoltages) -> EkfStep:
    """Run the EKF (eqs. 7.14-7.15, module docstring) over one chunk.

    Parameters
    ----------
    design : EkfDesign
        From :func:`discretise`.
    state : EkfState
        Carried state; not modified.
    deflection_nm : array_like
        Measured deflection y, nm.
    voltage_v : array_like or LeverVoltages
        Lever-sample voltage V at the same samples, V (only V² enters), or
        the V_R, V_sub series and α_R it is formed from (eq. 6.3), per sample
        in the kernel with the same rounding as
        :func:`afmtool.models.electrostatic.actuation_voltage`.

    Returns
    -------
    EkfStep
        Innovation and running mean, and the new state.  Chunked and
        single-call runs give bit-for-bit equal results.
    """
    y = np.ascontiguousarray(deflection_nm, dtype=np.float64)
    if isinstance(voltage_v, LeverVoltages):
        v_a = np.ascontiguousarray(voltage_v.v_r, dtype=np.float64)
        v_b = np.ascontiguousarray(voltage_v.v_sub, dtype=np.float64)
        alpha, beta = float(voltage_v.alpha_r), 1.0
    else:
        v_a = v_b = np.ascontiguousarray(voltage_v, dtype=np.float64)
        alpha, beta = 1.0, 0.0
    if y.ndim != 1 or y.shape != v_a.shape or y.shape != v_b.shape:
        raise ConfigError(f"deflection_nm and voltage_v must be 1-D of one length, got {y.shape} and {v_a.shape}")
    if state.ring.shape != (design.mean_window,):
        raise ConfigError(f"state has a mean window of {state.ring.shape[0]}, the design {design.mean_window}")
    vector = state.vector.copy()
    ring = state.ring.copy()
    out_e = np.empty_like(y)
    out_mean = np.empty_like(y)
    _ekf_kernel(y, v_a, v_b, alpha, beta, design.coef, vector, ring, out_e, out_mean)
    return EkfStep(EkfBlock(out_e, out_mean), EkfState(vector, ring))


def ekf_run(design: EkfDesign, deflection_nm, voltage_v, *, stats_from: int = 0) -> EkfStep:
    """:func:`ekf_update` from the initial state over a whole segment."""
    return ekf_update(design, EkfState.initial(design, stats_from=stats_from), deflection_nm, voltage_v)


class InnovationSums(NamedTuple):
    """The sums behind :class:`InnovationStats`, so that chunks run apart can be added up."""

    sum_e2: float  #: Σ ε², nm²
    sum_nis: float  #: Σ ε²/S
    count: int  #: samples counted

    def stats(self) -> InnovationStats:
        if self.count == 0:
            return InnovationStats(math.nan, math.nan, 0)
        return InnovationStats(math.sqrt(self.sum_e2 / self.count), self.sum_nis / self.count, self.count)


def ekf_from_prior(design: EkfDesign, lead: tuple | None, chunk: tuple, *, stats_from: int = 0) -> tuple[EkfBlock, InnovationSums]:
    """The EKF started from its prior (eq. 7.14) over ``lead``, then over ``chunk``: a chunk of a split capture.

    Parameters
    ----------
    design : EkfDesign
        From :func:`discretise`.
    lead, chunk : (deflection_nm, voltage) or None
        The warm-up samples just before the chunk (None: the chunk starts
        the stream), and the chunk; each as :func:`ekf_update` takes them.
    stats_from : int
        The first position in ``chunk`` whose innovation the sums count.

    Returns
    -------
    (EkfBlock, InnovationSums)
        The chunk's innovation and running mean, and its statistics sums.
        The running mean is exact once the lead is at least one mean window
        long; the state forgets the prior as :func:`ekf_forgetting_samples` measures.
    """
    state = EkfState.initial(design, stats_from=np.iinfo(np.int64).max)  # the lead counts nothing
    if lead is not None:
        state = ekf_update(design, state, *lead).state
    vector = state.vector.copy()
    vector[_STATS_FROM] = vector[_N] + max(int(stats_from), 0)
    step = ekf_update(design, EkfState(vector, state.ring), *chunk)
    v = step.state.vector
    return step.block, InnovationSums(float(v[_SUM_E2]), float(v[_SUM_NIS]), int(v[_COUNT]))


def ekf_forgetting_samples(design: EkfDesign, deflection_nm, voltage_v, *, residual: float = 1e-13) -> int | None:
    """Samples after which the EKF's output no longer depends on where it started, measured on a record.

    The filter is run from its prior over the record and again from its
    prior a quarter of the way in; the answer is the number of samples the
    second run needs before its innovation stays within ``residual`` of the
    first's largest innovation.  The EKF is nonlinear (the electrostatic
    force), so this is measured rather than derived from a pole radius.
    None if the two runs have not met within the record.
    """
    y = np.asarray(deflection_nm, dtype=np.float64)
    volts = voltage_v if isinstance(voltage_v, LeverVoltages) else np.asarray(voltage_v, dtype=np.float64)
    n = y.shape[0]
    offset = n // 4
    if n < 8:
        return None
    full = ekf_run(design, y, volts).block.innovation_nm[offset:]
    if isinstance(volts, LeverVoltages):
        late_volts = LeverVoltages(volts.v_r[offset:], volts.v_sub[offset:], volts.alpha_r)
    else:
        late_volts = volts[offset:]
    late = ekf_run(design, y[offset:], late_volts).block.innovation_nm
    apart = np.flatnonzero(np.abs(full - late) > residual * max(float(np.max(np.abs(full))), 1e-300))
    if apart.size == 0:
        return 0
    last = int(apart[-1]) + 1
    return None if last >= (n - offset) // 2 else last

