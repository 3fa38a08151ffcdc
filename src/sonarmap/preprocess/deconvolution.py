"""Wiener deconvolution of the beam pattern along the beam axis (paper eq. 2-4).

The image formation model of Teixeira et al. (eq. 2) is a convolution of the ideal intensity
``x`` with the beam pattern ``h`` *along the beams* of each range bin::

    y[i, j] = sum_m h[m] x[i, j - m] + n[i, j]

:func:`deconvolve` inverts it with the Wiener filter of eq. 4, ``G = H* / (|H|^2 + 1/SNR)``,
applied independently to every range bin (row).

Edge handling
-------------
``edge="pad"`` (default) uses the *linear* convolution model: beams outside the field of view are
zero, each row is zero-padded to ``L >= 2 n_beams - 1`` (rounded up to a fast FFT length) before the
real FFT, so the outer beams never wrap into each other and the result is not shifted along range
or azimuth.  ``edge="truncated"`` solves the same linear model as regularised least squares,
``x = argmin |y - A x|^2 + (1/SNR)|x|^2`` with ``A`` the convolution matrix *restricted to the
fan*, so echoes whose side lobes fall outside the fan are still deconvolved correctly (the
zero-padded FFT implicitly assumes the unobserved beams outside the fan read zero, which leaves
residual ghosts near the edges).  ``edge="circular"`` reproduces plain length-``n_beams`` FFT
(circular) convolution -
the model implicit in the paper authors' OpenCV code (without their one-bin shift along range,
which is a bug) - and is provided so that the paper's exact numbers can be matched.

Speed
-----
Transfer functions are cached per ``(psf bytes, 1/SNR, L, edge)``.  Because deconvolution is a
fixed linear operator on each row, for up to :data:`MATMUL_MAX_BEAMS` beams the cached transfer
function is also turned into an equivalent ``(n_beams, n_beams)`` matrix and applied with one BLAS
matrix product (``method="matmul"``), which is several times faster than per-row FFTs for
typical beam counts and gives the same result to float32 rounding.  ``method="fft"`` forces the
real-FFT path (``scipy.fft`` with ``workers=1``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import GeometryError, InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import as_image

__all__ = [
    "deconvolve",
    "wiener_filter",
    "wiener_matrix",
    "convolve_beams",
    "fft_length",
    "NoiseSpec",
    "MATMUL_MAX_BEAMS",
]

#: Beam counts up to this use the equivalent-matrix path when ``method="auto"``.
MATMUL_MAX_BEAMS = 512

Edge = Literal["pad", "circular", "truncated"]
Method = Literal["auto", "fft", "matmul"]
#: ``1/SNR``: a scalar, an array sampled uniformly over normalised frequency ``[0, 0.5]`` cycles per
#: beam (linearly interpolated), or a callable of the normalised frequency returning ``1/SNR``.
NoiseSpec = float | ArrayLike | Callable[[NDArray[np.float64]], ArrayLike]


def fft_length(n_beams: int, *, edge: Edge = "pad") -> int:
    """FFT length used along the beams: ``n_beams`` (circular) or a fast length ``>= 2 n_beams``."""
    if edge == "circular":
        return int(n_beams)
    if edge in ("pad", "truncated"):
        from scipy import fft as sfft

        return int(sfft.next_fast_len(2 * int(n_beams), real=True))
    raise InputError(f"edge: must be 'pad', 'circular' or 'truncated', got {edge!r}")


def _check_psf(psf: ArrayLike | SonarGeometry | None, n_beams: int | None) -> NDArray[np.float64] | None:
    if isinstance(psf, SonarGeometry):
        psf = psf.psf
    if psf is None:
        return None
    try:
        arr = np.asarray(psf, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("psf: not a numeric array") from None
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    if arr.ndim != 1 or arr.size == 0:
        raise InputError(f"psf: expected a 1-D beam pattern, got shape {arr.shape}")
    if n_beams is not None and arr.size != n_beams:
        raise GeometryError(
            f"psf: length {arr.size} does not match the image's {n_beams} beams "
            "(the beam pattern must have one tap per beam, centred at n_beams // 2)"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError("psf: contains NaN or infinite values")
    if np.any(arr < 0):
        raise InputError("psf: beam pattern must be non-negative")
    total = float(arr.sum())
    if total <= 0:
        raise InputError("psf: beam pattern sums to zero")
    return arr / total


def _noise_grid(noise: NoiseSpec, n_freq: int) -> NDArray[np.float64]:
    """``1/SNR`` sampled on the rfft frequencies ``k / L``, ``k = 0..n_freq-1`` (L = 2(n_freq-1) or so)."""
    freqs = np.linspace(0.0, 0.5, n_freq)
    if callable(noise):
        vals = np.asarray(noise(freqs), dtype=np.float64)
        vals = np.broadcast_to(vals, freqs.shape).astype(np.float64)
    else:
        arr = np.asarray(noise, dtype=np.float64)
        if arr.ndim == 0:
            vals = np.full(n_freq, float(arr))
        elif arr.ndim == 1 and arr.size >= 2:
            vals = np.interp(freqs, np.linspace(0.0, 0.5, arr.size), arr)
        else:
            raise InputError(
                f"noise: expected a scalar, a 1-D array of >= 2 samples over [0, 0.5] cycles/beam, "
                f"or a callable; got shape {arr.shape}"
            )
    if not np.all(np.isfinite(vals)) or np.any(vals < 0):
        raise InputError("noise: 1/SNR must be finite and >= 0")
    return vals


def _kernel_rfft(psf: NDArray[np.float64], n_fft: int) -> NDArray[np.complex128]:
    """rfft of the PSF placed so that tap ``n//2`` is at lag 0 (offsets wrap modulo ``n_fft``)."""
    n = psf.size
    c = n // 2
    h = np.zeros(n_fft, dtype=np.float64)
    lags = (np.arange(n) - c) % n_fft
    np.add.at(h, lags, psf)
    return np.fft.rfft(h)


@functools.lru_cache(maxsize=128)
def _wiener_cached(psf_bytes: bytes, noise_bytes: bytes, n_fft: int) -> NDArray[np.complex128]:
    psf = np.frombuffer(psf_bytes, dtype=np.float64)
    noise = np.frombuffer(noise_bytes, dtype=np.float64)
    H = _kernel_rfft(psf, n_fft)
    denom = (H.real**2 + H.imag**2) + noise
    with np.errstate(divide="ignore", invalid="ignore"):
        G = np.where(denom > 0, np.conj(H) / np.where(denom > 0, denom, 1.0), 0.0)
    G = G.astype(np.complex128)
    G.setflags(write=False)
    return G


def wiener_filter(
    psf: ArrayLike | SonarGeometry,
    *,
    noise: NoiseSpec = 1e-2,
    edge: Edge = "pad",
    n_fft: int | None = None,
) -> NDArray[np.complex128]:
    """Wiener transfer function ``G = H* / (|H|^2 + 1/SNR)`` on the rfft frequencies (eq. 4).

    Parameters
    ----------
    psf : array_like, shape (n_beams,), or SonarGeometry
        Beam pattern centred at index ``n_beams // 2`` (normalised to unit sum here).
    noise : float, array_like or callable
        ``1/SNR``.  A scalar; or an array sampled uniformly over normalised frequency
        ``[0, 0.5]`` cycles per beam (linearly interpolated onto the FFT grid); or a callable
        mapping normalised frequency (ndarray) to ``1/SNR``.
    edge : {"pad", "circular"}
        Linear (zero-padded) or circular convolution model; see the module notes.
    n_fft : int, optional
        FFT length; defaults to :func:`fft_length`.

    Returns
    -------
    ndarray, shape (n_fft // 2 + 1,), complex128
        Read-only, cached per ``(psf, noise, n_fft)``.

    Notes
    -----
    Eq. 3-4 of Teixeira et al. (2018).  With ``noise=0`` this is the plain inverse filter
    (frequencies where ``H = 0`` are set to zero).
    """
    p = _check_psf(psf, None)
    if p is None:
        raise InputError("psf: geometry has no beam pattern")
    L = fft_length(p.size, edge=edge) if n_fft is None else int(n_fft)
    if L < p.size:
        raise InputError(f"n_fft: {L} is shorter than the {p.size}-tap beam pattern")
    nz = _noise_grid(noise, L // 2 + 1)
    return _wiener_cached(p.tobytes(), nz.tobytes(), L)


@functools.lru_cache(maxsize=128)
def _matrix_cached(psf_bytes: bytes, noise_bytes: bytes, n_fft: int, n: int) -> NDArray[np.float32]:
    G = _wiener_cached(psf_bytes, noise_bytes, n_fft)
    eye = np.zeros((n, n_fft), dtype=np.float64)
    eye[np.arange(n), np.arange(n)] = 1.0
    # Row k of the result is the response to a unit impulse in beam k: x_hat = y @ M.
    M = np.fft.irfft(np.fft.rfft(eye, axis=1) * G, n=n_fft, axis=1)[:, :n]
    out = np.ascontiguousarray(M, dtype=np.float32)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=128)
def _lsq_matrix_cached(psf_bytes: bytes, noise: float) -> NDArray[np.float32]:
    psf = np.frombuffer(psf_bytes, dtype=np.float64)
    n = psf.size
    c = n // 2
    j = np.arange(n)[:, None]
    k = np.arange(n)[None, :]
    m = j - k + c
    A = np.where((m >= 0) & (m < n), psf[np.clip(m, 0, n - 1)], 0.0)  # y = A x (truncated)
    W = np.linalg.solve(A.T @ A + noise * np.eye(n), A.T)  # x_hat = W y
    out = np.ascontiguousarray(W.T, dtype=np.float32)  # row form: x_hat = y @ W.T
    out.setflags(write=False)
    return out


def _scalar_noise(noise: NoiseSpec) -> float:
    if callable(noise) or np.ndim(noise) != 0:
        raise InputError("noise: edge='truncated' supports only a scalar 1/SNR")
    val = float(noise)  # type: ignore[arg-type]
    if not np.isfinite(val) or val < 0:
        raise InputError(f"noise: 1/SNR must be finite and >= 0 (got {val})")
    if val == 0:
        raise InputError("noise: edge='truncated' needs 1/SNR > 0 (the system may be singular)")
    return val


def _operator(p: NDArray[np.float64], noise: NoiseSpec, edge: Edge) -> NDArray[np.float32]:
    """Row operator ``M`` with ``x_hat = y @ M`` for any edge model (cached)."""
    if edge == "truncated":
        return _lsq_matrix_cached(p.tobytes(), _scalar_noise(noise))
    L = fft_length(p.size, edge=edge)
    nz = _noise_grid(noise, L // 2 + 1)
    return _matrix_cached(p.tobytes(), nz.tobytes(), L, p.size)


def wiener_matrix(
    psf: ArrayLike | SonarGeometry,
    *,
    noise: NoiseSpec = 1e-2,
    edge: Edge = "pad",
) -> NDArray[np.float32]:
    """The deconvolution as a matrix ``M`` (n_beams, n_beams): ``deconvolve(y) == y @ M``.

    For ``edge="pad"``/``"circular"`` it is built once from the cached transfer function of
    :func:`wiener_filter`; for ``edge="truncated"`` it is the regularised least-squares inverse
    ``M = ((A^T A + noise I)^-1 A^T)^T`` of the truncated convolution matrix ``A``.  Read-only.
    """
    p = _check_psf(psf, None)
    if p is None:
        raise InputError("psf: geometry has no beam pattern")
    return _operator(p, noise, edge)


def _apply_fft(img: NDArray[np.float32], G: NDArray[np.complex128], n_fft: int) -> NDArray[np.float32]:
    from scipy import fft as sfft

    n = img.shape[1]
    spec = sfft.rfft(img, n=n_fft, axis=1, workers=1)  # zero-pads to n_fft; complex64
    spec *= G.astype(np.complex64)
    out = sfft.irfft(spec, n=n_fft, axis=1, workers=1, overwrite_x=True)
    return np.ascontiguousarray(out[:, :n], dtype=np.float32)


def deconvolve(
    image: ArrayLike,
    psf: ArrayLike | SonarGeometry | None,
    *,
    noise: NoiseSpec = 1e-2,
    clip_negative: bool = False,
    edge: Edge = "truncated",
    method: Method = "auto",
) -> NDArray[np.float32]:
    """Remove the beam pattern from an image by Wiener deconvolution along the beams.

    Parameters
    ----------
    image : array_like, shape (n_bins, n_beams)
        Intensities (any real dtype; converted to float32).
    psf : array_like, shape (n_beams,), SonarGeometry or None
        Beam pattern centred at index ``n_beams // 2`` (``geometry.psf``); normalised to unit sum.
        ``None`` (or a geometry without a PSF) means no spreading: the image is returned
        unchanged (apart from ``clip_negative``).
    noise : float, array_like or callable
        ``1/SNR`` of eq. 4 (see :func:`wiener_filter` for the frequency-dependent forms).
    clip_negative : bool
        Set negative outputs (ringing of the inverse filter) to zero.  Off by default so the
        operator stays linear.
    edge : {"pad", "circular", "truncated"}
        ``"pad"``: linear convolution model, zero-padded FFT (no wrap at the fan edges).
        ``"circular"``: plain FFT circular convolution over ``n_beams``, as in the authors' code.
        ``"truncated"``: regularised least squares for the linear model observed only inside the
        fan (no assumption about the unobserved beams outside it); scalar ``noise`` only, always
        a matrix product.  Best ghost suppression near the fan edges (see ``docs/preprocessing.md``);
        the default.  Use ``"pad"`` for a frequency-dependent ``noise``.
    method : {"auto", "fft", "matmul"}
        ``"fft"``: real FFT along the beams with the cached transfer function.  ``"matmul"``:
        the same linear operator as a cached ``n_beams x n_beams`` matrix.  ``"auto"`` picks
        ``matmul`` up to :data:`MATMUL_MAX_BEAMS` beams.

    Returns
    -------
    ndarray, shape (n_bins, n_beams), float32
        New array; the input is not modified.  No shift along range or azimuth.

    Raises
    ------
    InputError
        NaN/inf or non-2-D image, bad ``noise``/``psf`` values, unknown ``edge``/``method``.
    GeometryError
        If the PSF length differs from the number of beams.

    Notes
    -----
    Eq. 3 (model) and eq. 4 (Wiener filter ``G = H*/(|H|^2 + 1/SNR)``) of Teixeira et al. (2018).
    """
    img = as_image(image, "image")
    p = _check_psf(psf, img.shape[1])
    if method not in ("auto", "fft", "matmul"):
        raise InputError(f"method: must be 'auto', 'fft' or 'matmul', got {method!r}")
    L = fft_length(img.shape[1], edge=edge)
    if p is None:
        out = img.copy()
    else:
        use_mm = (
            edge == "truncated"
            or method == "matmul"
            or (method == "auto" and img.shape[1] <= MATMUL_MAX_BEAMS)
        )
        if use_mm:
            out = img @ _operator(p, noise, edge)
        else:
            nz = _noise_grid(noise, L // 2 + 1)
            out = _apply_fft(img, _wiener_cached(p.tobytes(), nz.tobytes(), L), L)
    if clip_negative:
        np.maximum(out, 0.0, out=out)
    return out


def convolve_beams(
    image: ArrayLike, psf: ArrayLike | SonarGeometry, *, edge: Edge = "pad"
) -> NDArray[np.float32]:
    """Forward model of eq. 2-3: spread each beam with the beam pattern (no noise).

    ``edge="pad"``: linear convolution, beams outside the fan are zero; ``"circular"``: circular
    over ``n_beams``.  Useful for tests and simulation.
    """
    img = as_image(image, "image")
    p = _check_psf(psf, img.shape[1])
    if p is None:
        return img.copy()
    L = fft_length(img.shape[1], edge=edge)
    H = _kernel_rfft(p, L)
    spec = np.fft.rfft(img.astype(np.float64), n=L, axis=1) * H
    return np.fft.irfft(spec, n=L, axis=1)[:, : img.shape[1]].astype(np.float32)
