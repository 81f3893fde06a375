"""The adaptive-optics loop's controller and its transfer functions (pure numpy on command vectors).

Timing (one frame = ``T = 1 / fs``).  During frame ``k`` the DM holds the command ``u_k``; the sensor integrates
the residual ``r = disturbance - correction`` over the frame and its measurement ``e_k`` (in command space:
the residual phase fitted by the DM) reaches the controller at the end of the frame.  The leaky integrator
makes ``c_{k+1} = leak c_k + gain e_k``; a delay line holds ``c`` back by ``delay - 1`` frames, so the command
of frame ``k + 1`` is ``u_{k+1} = c`` delayed: ``delay`` is the **total** loop delay in frames, from the frame
measured to the frame corrected, ``delay >= 1`` (1: corrected on the very next frame; the classical
"two-frame" loop is ``delay = 2``: half a frame of WFS integration, one of read-out and computation, half of
DM hold).

A fractional delay ``n + a`` (``0 <= a < 1``) is an integer buffer of ``n`` frames and linear interpolation
between consecutive commands, ``(1 - a) c_{k-n} + a c_{k-n-1}``.  That is exact, not an approximation, for a
loop whose command arrives ``a`` of a frame late: the DM holds ``c_{k-n-1}`` for the first ``a`` of the frame
and ``c_{k-n}`` for the rest, and a frame-integrating sensor sees their average.

Transfer functions, ``z = exp(2 pi i f / fs)``:

* ``model="discrete"`` (default; exact for the frame-averaged residual of this loop, what the sensor sees and
  what a frame-by-frame simulation computes):
  ``H_OL(z) = gain z^-n ((1 - a) + a z^-1) / (1 - leak z^-1)``;
* ``model="hybrid"`` (continuous residual, Madec 1999): integrator ``gain / (1 - leak e^{-sT})`` times the
  WFS's integration over one frame and the DM's zero-order hold, each ``(1 - e^{-sT}) / (sT)``, times the
  pure computational delay ``exp(-2 pi i f tau)``, ``tau = (delay - 1) T``, ``s = 2 pi i f``.  It equals the
  discrete one times ``sinc^2(f / fs)`` for an integer delay (below ``fs / 10``: within 0.3 dB).

Rejection ``1 / (1 + H_OL)``; closed loop ``H_OL / (1 + H_OL)``.  Stability: the discrete characteristic
polynomial ``z^{n+1} - leak z^n + gain (1 - a) z + gain a`` must have all its roots strictly inside the unit
circle, decided by the Schur-Cohn recursion (no root finding; a root on the circle counts as unstable).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ..validation import ConfigError, check_number

__all__ = [
    "Controller",
    "DelayLine",
    "LeakyIntegrator",
    "characteristic_polynomial",
    "closed_loop_bandwidth",
    "closed_loop_stable",
    "closed_loop_tf",
    "open_loop_tf",
    "pseudo_open_loop",
    "rejection_tf",
]


def _check_delay(delay: float, lo: float) -> tuple[int, float]:
    d = check_number("loop.delay_frames", delay, lo, 1000, unit="frames")
    n = int(np.floor(d))
    return n, d - n


class LeakyIntegrator:
    """``c_{k+1} = leak c_k + gain e_k`` on command vectors (state zero until the first step)."""

    def __init__(self, gain: float, leak: float = 1.0):
        self.gain = check_number("loop.gain", gain, 0)
        self.leak = check_number("loop.leak", leak, 0, 1)
        self.state = None

    def step(self, error: np.ndarray) -> np.ndarray:
        e = np.asarray(error, float)
        self.state = self.gain * e if self.state is None else self.leak * self.state + self.gain * e
        return self.state

    def reset(self) -> None:
        self.state = None


class DelayLine:
    """Holds values back by a real number of steps ``delay = n + a``: :meth:`push` of ``x_k`` returns
    ``(1 - a) x_{k-n} + a x_{k-n-1}`` (zero before the first value); an integer delay is a plain buffer."""

    def __init__(self, delay: float):
        self.n, self.a = _check_delay(delay, 0)
        self.delay = self.n + self.a
        self._buf: deque = deque(maxlen=self.n + 2)

    def push(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        self._buf.appendleft(x)  # _buf[j] = x_{k-j}
        b = self._buf
        zero = np.zeros_like(x)
        now = b[self.n] if len(b) > self.n else zero
        if self.a == 0:
            return now.copy()
        before = b[self.n + 1] if len(b) > self.n + 1 else zero
        return (1 - self.a) * now + self.a * before

    def reset(self) -> None:
        self._buf.clear()


class Controller:
    """Leaky integrator plus delay line: :meth:`step` takes the measurement ``e_k`` of frame ``k`` (command
    space, the residual's fit) and returns the command the DM holds during frame ``k + 1``.  ``delay`` is the
    total loop delay in frames (>= 1, real); ``limit`` (optional, rad) clips the integrator's state (anti-windup
    at the DM's stroke)."""

    def __init__(self, gain: float, delay: float = 2.0, leak: float = 1.0, limit: float | None = None):
        self.integrator = LeakyIntegrator(gain, leak)
        n, a = _check_delay(delay, 1)
        self.delay = n + a
        self.line = DelayLine(self.delay - 1)
        self.limit = None if limit is None else check_number("loop.limit", limit, 0, open_lo=True, unit="rad")

    @property
    def gain(self) -> float:
        return self.integrator.gain

    @property
    def leak(self) -> float:
        return self.integrator.leak

    def step(self, measurement: np.ndarray) -> np.ndarray:
        c = self.integrator.step(measurement)
        if self.limit is not None:
            np.clip(c, -self.limit, self.limit, out=c)
        return self.line.push(c)

    def reset(self) -> None:
        self.integrator.reset()
        self.line.reset()


def pseudo_open_loop(residual: np.ndarray, applied: np.ndarray, dm=None) -> np.ndarray:
    """The open-loop (disturbance) equivalent of a closed-loop measurement: ``residual + correction``, the
    correction being ``applied`` (the commands the DM held while ``residual`` was measured; the loop's sign
    ``residual = disturbance - correction``): in command space without ``dm``, or as phase on the crop with
    ``dm`` (``residual`` (..., A, A) rad + ``dm.surface(applied)``)."""
    r = np.asarray(residual)
    return r + (np.asarray(applied) if dm is None else dm.surface(applied))


def open_loop_tf(f, fs: float, gain: float, delay_frames: float, leak: float = 1.0,
                 model: str = "discrete") -> np.ndarray:
    """Open-loop transfer function ``H_OL`` at frequencies ``f`` (Hz) of the loop at frame rate ``fs`` (Hz);
    see the module's docstring for the two models."""
    fs = check_number("loop.fs", fs, 0, open_lo=True, unit="Hz")
    g = check_number("loop.gain", gain, 0)
    lk = check_number("loop.leak", leak, 0, 1)
    n, a = _check_delay(delay_frames, 1)
    f = np.asarray(f, float)
    zi = np.exp(-2j * np.pi * f / fs)  # z^-1
    integ = g / (1 - lk * zi)
    if model == "discrete":
        return integ * zi ** n * ((1 - a) + a * zi)
    if model == "hybrid":
        sT = 2j * np.pi * f / fs
        with np.errstate(invalid="ignore", divide="ignore"):
            zoh = np.where(sT == 0, 1.0, (1 - zi) / np.where(sT == 0, 1.0, sT))
        return integ * zoh * zoh * np.exp(-sT * (n + a - 1))
    raise ConfigError("loop.model", f"expected discrete or hybrid, got {model!r}")


def rejection_tf(f, fs: float, gain: float, delay_frames: float, leak: float = 1.0,
                 model: str = "discrete") -> np.ndarray:
    """Error (rejection) transfer function ``1 / (1 + H_OL)``: residual over disturbance."""
    return 1.0 / (1.0 + open_loop_tf(f, fs, gain, delay_frames, leak, model))


def closed_loop_tf(f, fs: float, gain: float, delay_frames: float, leak: float = 1.0,
                   model: str = "discrete") -> np.ndarray:
    """Closed-loop transfer function ``H_OL / (1 + H_OL)``: correction over disturbance."""
    h = open_loop_tf(f, fs, gain, delay_frames, leak, model)
    return h / (1.0 + h)


def characteristic_polynomial(gain: float, delay_frames: float, leak: float = 1.0) -> np.ndarray:
    """Coefficients, highest power first, of ``z^{n+1} - leak z^n + gain (1 - a) z + gain a`` (``delay = n + a``):
    the closed loop's poles are its roots."""
    n, a = _check_delay(delay_frames, 1)
    p = np.zeros(n + 2)
    p[0], p[1] = 1.0, -float(leak)
    p[n] += gain * (1 - a)
    p[n + 1] += gain * a
    return p


def _schur_cohn_stable(p: np.ndarray) -> bool:
    """All roots of ``p`` (highest power first) strictly inside the unit circle (Schur-Cohn recursion: with
    ``|p(0)| < |lead|``, ``(conj(lead) p - p(0) p*) / z`` has one root fewer inside, by Rouche's theorem)."""
    a = np.asarray(p, complex)
    while len(a) > 1:
        lead, const = a[0], a[-1]
        if not abs(const) < abs(lead):
            return False
        rev = np.conj(a[::-1])  # p*(z) = z^m conj(p(1/conj z))
        a = (np.conj(lead) * a - const * rev)[:-1]  # the constant term cancels: divide by z
    return True


def closed_loop_stable(gain: float, delay_frames: float, leak: float = 1.0) -> bool:
    """Whether the discrete loop is (asymptotically) stable: the characteristic polynomial's roots strictly
    inside the unit circle (Schur-Cohn; marginal counts as unstable)."""
    return _schur_cohn_stable(characteristic_polynomial(gain, delay_frames, leak))


def closed_loop_bandwidth(fs: float, gain: float, delay_frames: float, leak: float = 1.0,
                          model: str = "discrete") -> float:
    """The -3 dB closed-loop bandwidth (Hz): the lowest frequency where ``|H_OL / (1 + H_OL)|^2`` falls to 1/2
    (``fs / 2`` if it never does below Nyquist)."""
    from scipy.optimize import brentq

    def excess(f):
        return float(np.abs(closed_loop_tf(f, fs, gain, delay_frames, leak, model)) ** 2 - 0.5)

    f = np.linspace(1e-6, 0.5, 4097) * fs
    v = np.abs(closed_loop_tf(f, fs, gain, delay_frames, leak, model)) ** 2 - 0.5
    below = np.flatnonzero(v < 0)
    if len(below) == 0:
        return fs / 2
    i = below[0]
    return float(f[0]) if i == 0 else float(brentq(excess, f[i - 1], f[i], xtol=1e-9 * fs))
