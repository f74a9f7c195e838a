"""Temporal filters of weight curves after the solve: One Euro (causal) and Gaussian (zero phase).

For the per-frame methods, whose curves jitter where the markers do. :func:`filter_weights` is the
one entry point; the responses below are computed by :func:`lowpass_response`,
:func:`one_euro_cutoff` and :func:`gaussian_response` (and tested against the filters).

* One Euro (Casiez, Roussel, Vogel 2012 [1]): a first-order low-pass
  ``y_n = a x_n + (1 - a) y_{n-1}``, ``a = 1 / (1 + fps / (2 pi f_c))``, whose cutoff follows the
  low-passed speed: ``f_c = min_cutoff + beta |dx/dt|``. For a fixed ``f_c`` the magnitude
  response at frequency ``f`` (``omega = 2 pi f / fps``) is::

      |H(f)|^2 = a^2 / (1 - 2 (1 - a) cos(omega) + (1 - a)^2)                          (R1)

  (:func:`lowpass_response`), -3 dB at ``cos omega_c = 1 - a^2 / (2 (1 - a))`` (about ``f_c``
  for ``f_c << fps``), delay ``(1 - a) / a`` frames = ``1 / (2 pi f_c)`` seconds at low
  frequencies. With ``beta = 0`` the One Euro filter *is* this low-pass at ``min_cutoff``.

  Cutoff against speed (``beta > 0``). The filter's speed estimate is ``(x_n - y_{n-1}) fps``,
  taken against its own lagging output. On a ramp ``x = v t`` the low-pass settles to a
  constant lag ``L = (1 - a) v / (a fps)`` (from ``y_n = a x_n + (1 - a) y_{n-1}`` with
  ``y_n = x_n - L``), so the estimate is ``v T_e + L`` per frame = ``v / a``: the filter sees
  ``1/a`` times the true speed. The cutoff is therefore the fixed point
  ``f_c = min_cutoff + beta v / a(f_c)``; with ``a = r / (1 + r)``, ``r = 2 pi f_c / fps`` this is
  the quadratic ``kappa f_c^2 - kappa (min_cutoff + beta v) f_c - beta v = 0``, ``kappa = 2 pi / fps``::

      f_c(v) = ((min_cutoff + beta v) + sqrt((min_cutoff + beta v)^2 + 4 beta v / kappa)) / 2       (R2)

  (:func:`one_euro_cutoff`), about ``sqrt(beta v fps / (2 pi))`` for fast motion, and the lag
  behind a ramp is ``L(v) = v (1 - a) / (a fps)`` ~ ``v / (2 pi f_c(v))``: it grows like
  ``sqrt(v)``, not like ``v`` as for a fixed cutoff. On a sine the cutoff swings with the speed
  and the filter is no longer linear; its attenuation is never below (R1) at ``min_cutoff`` and
  lies well above it (measured table in ``docs/controls.md``): fast motion is followed, slow
  jitter is removed.
* Gaussian (zero phase, whole take): :func:`core.solvers.local.smooth_weights` (one
  implementation), ``H(f) = sum_k g_k cos(omega k)`` ~ ``exp(-(sigma omega)^2 / 2)``
  (:func:`gaussian_response`), -3 dB at ``f = fps sqrt(ln 2) / (2 pi sigma)`` = 0.1325 fps /
  sigma (sigma in frames).

Both are convex combinations of input samples (non-negative taps summing to 1), so weights stay
inside any box the solver imposed.

References
----------
.. [1] G. Casiez, N. Roussel, D. Vogel, "1 Euro Filter: A Simple Speed-based Low-pass Filter for
       Noisy Input in Interactive Systems", CHI 2012, pp. 2527-2530.
"""

from __future__ import annotations

import difflib

import numpy as np

from ..solvers.local import smooth_weights
from .inputs import as_fps, as_weights

__all__ = ["FILTERS", "lowpass_alpha", "lowpass_response", "one_euro_cutoff", "gaussian_response", "one_euro",
           "OneEuro", "filter_weights"]


FILTERS = ("none", "gaussian", "one_euro")


def lowpass_alpha(cutoff, fps) -> np.ndarray:
    """Smoothing factor of the first-order low-pass at ``cutoff`` Hz:
    ``a = 1 / (1 + tau / T_e)``, ``tau = 1 / (2 pi f_c)``, ``T_e = 1 / fps`` (Casiez et al. 2012 [1])."""
    r = 2.0 * np.pi * np.asarray(cutoff, dtype=np.float64) / as_fps(fps)
    return r / (1.0 + r)


def lowpass_response(freq, fps, cutoff) -> np.ndarray:
    """Magnitude response (R1) of the One Euro filter's first-order low-pass at a fixed cutoff:
    ``|H| = a / sqrt(1 - 2 (1 - a) cos(2 pi f / fps) + (1 - a)^2)`` (module docstring)."""
    a = lowpass_alpha(cutoff, fps)
    w = 2.0 * np.pi * np.asarray(freq, dtype=np.float64) / as_fps(fps)
    return a / np.sqrt(1.0 - 2.0 * (1.0 - a) * np.cos(w) + (1.0 - a) ** 2)


def one_euro_cutoff(speed, fps, min_cutoff: float = 1.0, beta: float = 0.0):
    """Steady-state cutoff (Hz) and lag of the One Euro filter on a ramp of ``speed``: (R2) of
    the module docstring. Returns ``(f_c, lag)`` (lag in the signal's units: ``v (1 - a) / (a fps)``)."""
    v = np.abs(np.asarray(speed, dtype=np.float64))
    kappa = 2.0 * np.pi / as_fps(fps)
    b = min_cutoff + beta * v
    fc = 0.5 * (b + np.sqrt(b * b + 4.0 * beta * v / kappa))
    a = lowpass_alpha(fc, fps)
    return fc, v * (1.0 - a) / (a * as_fps(fps))


def gaussian_response(freq, fps, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """Frequency response of the zero-phase Gaussian of :func:`core.solvers.local.smooth_weights`
    (``scipy.ndimage.gaussian_filter1d``, kernel truncated at ``truncate * sigma`` frames):
    ``H(f) = sum_k g_k cos(2 pi f k / fps)``, real (no phase), ~ ``exp(-2 (pi sigma f / fps)^2)``."""
    s = float(sigma)
    w = 2.0 * np.pi * np.asarray(freq, dtype=np.float64) / as_fps(fps)
    if s == 0:
        return np.ones_like(w)
    r = int(truncate * s + 0.5)
    k = np.arange(-r, r + 1)
    g = np.exp(-0.5 * (k / s) ** 2)
    g /= g.sum()
    return np.tensordot(np.cos(np.multiply.outer(w, k)), g, axes=([-1], [0]))


def one_euro(W, fps, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0) -> np.ndarray:
    """The One Euro filter (Casiez, Roussel, Vogel 2012 [1]) on every column of ``W``, causal.

    Per sample n (period ``T_e = 1 / fps``)::

        dx_n  = (x_n - y_{n-1}) / T_e                 speed against the previous output
        ed_n  = LP(dx_n; d_cutoff)                    its first-order low-pass
        f_n   = min_cutoff + beta |ed_n|              cutoff that follows the speed
        y_n   = LP(x_n; f_n)                          y_n = a x_n + (1 - a) y_{n-1}

    with ``a = lowpass_alpha(f, fps)``; ``y_0 = x_0``, ``ed_0 = 0``. Response: module docstring.

    Parameters
    ----------
    W : (T, K) float, finite (fill gaps first, :func:`core.gaps.fill_gaps`)
    fps : float > 0
    min_cutoff : float > 0, Hz (jitter at rest)
    beta : float >= 0, speed coefficient (lag during fast motion)
    d_cutoff : float > 0, Hz (the derivative's low-pass)

    Returns
    -------
    (T, K) float64
    """
    W = as_weights(W)
    f = as_fps(fps)
    for name, v, lo in (("min_cutoff", min_cutoff, 0.0), ("d_cutoff", d_cutoff, 0.0)):
        if not (np.isfinite(v) and v > lo):
            raise ValueError(f"{name}: expected a positive frequency in Hz, got {v}")
    if not (np.isfinite(beta) and beta >= 0):
        raise ValueError(f"beta: expected a finite number >= 0, got {beta}")
    if not np.isfinite(W).all():
        raise ValueError("W: contains NaN/inf; fill the gaps first (core.gaps.fill_gaps)")
    out = np.empty_like(W)
    if not len(W):
        return out
    state = OneEuro(f, min_cutoff, beta, d_cutoff)
    for n in range(len(W)):
        out[n] = state.step(W[n])
    # each output is a convex combination of inputs: within their range but for rounding
    return np.clip(out, W.min(axis=0), W.max(axis=0), out=out)


class OneEuro:
    """The One Euro filter's state, one sample at a time (a live stream; :func:`one_euro` runs
    it over a whole take): ``step(x_n)`` returns ``y_n`` of :func:`one_euro`'s recursion.
    Settings as :func:`one_euro` (checked there; here ``fps`` is trusted)."""

    def __init__(self, fps: float, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0):
        self.fps, self.min_cutoff, self.beta = float(fps), min_cutoff, beta
        self.ad = lowpass_alpha(d_cutoff, self.fps)
        self.two_pi_te = 2.0 * np.pi / self.fps
        self.y = None
        self.ed = None

    def step(self, x) -> np.ndarray:
        """``y_n`` for the sample ``x_n`` (K,); the first sample passes unchanged."""
        x = np.asarray(x, dtype=np.float64)
        if self.y is None:
            self.y = x.copy()
            self.ed = np.zeros(x.shape)
            return self.y
        f = self.fps
        self.ed = self.ad * ((x - self.y) * f) + (1.0 - self.ad) * self.ed
        r = self.two_pi_te * (self.min_cutoff + self.beta * np.abs(self.ed))
        a = r / (1.0 + r)
        self.y = a * x + (1.0 - a) * self.y
        return self.y


def filter_weights(W, fps, kind: str = "one_euro", *, sigma: float = 1.0, min_cutoff: float = 1.0,
                   beta: float = 0.0, d_cutoff: float = 1.0) -> np.ndarray:
    """Post-solve temporal filter of weight curves, one entry point for every per-frame method.

    Parameters
    ----------
    W : (T, K) float, finite
    fps : float > 0
    kind : {"none", "gaussian", "one_euro"}
        ``"gaussian"``: zero-phase Gaussian of ``sigma`` frames over the whole take
        (:func:`core.solvers.local.smooth_weights`, response :func:`gaussian_response`);
        ``"one_euro"``: causal One Euro (:func:`one_euro`); ``"none"``: a copy.
    sigma, min_cutoff, beta, d_cutoff
        The filters' settings (module docstring for their responses).

    Returns
    -------
    (T, K) float64. Both filters average input samples with non-negative weights summing to 1,
    so any box bounds of the solve still hold.
    """
    if kind not in FILTERS:
        close = difflib.get_close_matches(str(kind), FILTERS, n=1)
        raise ValueError(f"kind: expected one of {FILTERS}, got {kind!r}" + (f"; did you mean {close[0]!r}?" if close else ""))
    W = as_weights(W)
    if kind == "none":
        return W.copy()
    if kind == "gaussian":
        if not np.isfinite(W).all():
            raise ValueError("W: contains NaN/inf; fill the gaps first (core.gaps.fill_gaps)")
        as_fps(fps)
        return smooth_weights(W, sigma)
    return one_euro(W, fps, min_cutoff, beta, d_cutoff)
