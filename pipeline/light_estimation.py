"""Least-squares light estimation T l = I_c (section 5.2 of seeds/000), made robust.

T holds one SH transfer vector per valid pixel (world frame), I_c the pixel's linear
luminance. Beyond the paper's plain least squares:

* the colour image is linearised (sRGB decode) before fitting: the model is linear in
  radiance, and 8-bit sRGB is not;
* clipped and near-black pixels are left out;
* Tikhonov regularisation grows with the band (l(l+1)), so directions of the light that
  the observed normals cannot constrain are damped towards zero rather than invented
  (bands 2-3 firmly: a diffuse image barely sees them, and left free they absorb albedo
  texture and depth errors that then tilt band 1, the dominant direction);
  the number of bands is also cut back while the column-scaled normal matrix is too
  ill-conditioned, and the conditioning is reported;
* one unknown albedo per material segment (the pipeline never lets the ground share one
  with what stands on it), solved by alternation with the light (24 passes: the
  alternation converges slowly, and held out by map 24 beat 8;
  docs/decisions/0052-no-huber-24-passes.md);
* optionally, iteratively re-weighted least squares (Huber weights on the relative
  residual, `robust_threshold` > 0). Off by default: held out by map the fit is better
  without it, most of all in back-lit views, whose pixels darker than predicted it
  down-weights (decision 0052).

The fit's confidence is light_confidence.py's, the smoothing over frames
temporal_filter.py's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from arlight.core.frames import Confidence
from arlight.pipeline import sh
from arlight.pipeline.channels import channel_max
from arlight.pipeline.color import LUMA
from arlight.pipeline.config import EstimationParams
from arlight.pipeline.light_confidence import (
    FitEvidence,
    confidence_value,
    low_confidence_reason,
)

CLIP_LEVEL = 0.98  # linear value above which a channel is treated as clipped
DARK_LEVEL = 0.004  # linear luminance below which a pixel carries only noise
MAX_CONDITION = 1e5  # of the column-scaled normal matrix; above it, drop the top band


@dataclass
class LightEstimate:
    """sh: (C,) luminance radiance SH (frame of T); sh_rgb: (3, C) or None."""

    sh: np.ndarray
    confidence: Confidence
    sh_rgb: np.ndarray | None = None
    residual_rel: float = float("nan")
    bounce_scale: float = 0.0  # beta of the one-bounce term (0 when not modelled)
    horizon_prior_used: bool = False  # the fit was redone with the below-horizon prior
    fit: FitState | None = None  # what the fit ended with (for cues fitted beside it)


@dataclass(frozen=True)
class FitState:
    """The final fit's linear system, for terms fitted beside the SH (compact_light).

    rows: (M,) indices of the fitted pixels among the inputs' rows; design: (M, n) their
    columns [T | B] (n = bands^2 [+ 1 with the bounce]); albedo, weights: (M,) per-pixel
    albedo and robust weights; lum: (M,) linear luminance; rgb: (M, 3); penalty: (n, n)
    the regulariser, relative to the mean diagonal of the normal matrix."""

    rows: np.ndarray
    design: np.ndarray
    albedo: np.ndarray
    weights: np.ndarray
    lum: np.ndarray
    rgb: np.ndarray
    penalty: np.ndarray
    bands: int


def _band_penalty(bands: int) -> np.ndarray:
    per_band = np.array([max(1.0, l * (l + 1.0)) for l in range(bands)])
    return np.repeat(per_band, [2 * l + 1 for l in range(bands)])


def _condition(gram: np.ndarray) -> float:
    d = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    scaled = gram / d[:, None] / d[None, :]
    ev = np.linalg.eigvalsh(scaled)
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


def choose_bands(transfer: np.ndarray, max_bands: int) -> tuple[int, float]:
    """Largest band count whose (column-scaled) normal matrix has condition <= MAX_CONDITION."""
    gram = transfer.T @ transfer
    cond = float("inf")
    for bands in range(max_bands, 0, -1):
        n = bands * bands
        cond = _condition(gram[:n, :n])
        if cond <= MAX_CONDITION:
            return bands, cond
    return 1, cond


def below_horizon_gram(
    up: np.ndarray, bands: int, ground_albedo: float = 0.3, samples: int = 2048
) -> np.ndarray:
    """Q such that l^T Q l = integral over w . up < 0 of (L(w) - L_ground)^2 dw, where
    L_ground = ground_albedo / pi * E_up is the radiance of a Lambertian ground lit by the
    upper hemisphere of the same light (E_up = its irradiance on a surface facing `up`).
    Light from below the horizon of the surface a scene stands on is, for that scene, the
    glow of such a ground, not a lobe of its own. `up`: unit, frame of l."""
    up = np.asarray(up, dtype=np.float64)
    dirs = sh.fibonacci_sphere(samples)
    weight = 4.0 * math.pi / samples
    cos_up = dirs @ up
    y = sh.sh_basis(dirs, bands)
    e_up = (y * np.maximum(cos_up, 0.0)[:, None]).sum(axis=0) * weight  # E_up = e_up . l
    d = y[cos_up < 0.0] - (ground_albedo / math.pi) * e_up
    return d.T @ d * weight


def solve_regularised(
    transfer: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray,
    bands: int,
    regularization: float,
    bounce: np.ndarray | None = None,
    prior: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """argmin_{l, beta} sum w (T l + beta B - I)^2 + lambda mean(diag) sum_z (l(l+1) l_z)^2
    + mean(diag) l^T P l.

    Returns (l, beta). beta (>= 0) scales the one-bounce light B of the occluders (it is the
    scene's mean albedo over pi, unknown); without `bounce` it is 0. P (C x C, optional) is
    an extra quadratic prior on l, relative to the mean diagonal of the normal matrix.
    """
    design = _design(transfer, bands, bounce)
    gram = design.T @ (design * weights[:, None])
    return _solve_weighted(
        design, gram, weights * target, bands, regularization, bounce is not None, prior
    )


def _design(transfer: np.ndarray, bands: int, bounce: np.ndarray | None) -> np.ndarray:
    """(M, n [+ 1]): the first bands^2 transfer columns, and B as the last column."""
    t = transfer[:, : bands * bands]
    return t if bounce is None else np.column_stack([t, bounce])


def penalty_matrix(
    bands: int, regularization: float, prior: np.ndarray | None, with_bounce: bool
) -> np.ndarray:
    """The fit's regulariser on [l | beta], relative to the mean diagonal of the normal
    matrix: the band penalty, the prior, and `regularization` on beta."""
    n = bands * bands
    penalty = np.diag(regularization * _band_penalty(bands) ** 2)
    if prior is not None:
        penalty = penalty + prior[:n, :n]
    if with_bounce:
        penalty = np.pad(penalty, ((0, 1), (0, 1)))
        penalty[n, n] = regularization
    return penalty


class SegmentGrams:
    """A^T diag(g) A for weights g = w a^2 that are a per-segment albedo a squared times a
    robust weight w that is 1 on most samples: sum_g a_g^2 G_g (each segment's A_g^T A_g,
    made once) plus the samples with w < 1 alone. The same matrix as the direct product to
    rounding, for a quarter of its work when a quarter of the samples are down-weighted
    (docs/decisions/0042-overlapped-frames.md, "LightEst")."""

    def __init__(self, design: np.ndarray, labels: np.ndarray | None):
        self.design = design
        self.labels = np.zeros(len(design), np.int64) if labels is None else labels
        count = int(self.labels.max()) + 1 if len(design) else 1
        order = np.argsort(self.labels, kind="stable")
        bounds = np.searchsorted(self.labels[order], np.arange(count + 1))
        self._order, self._bounds = order, bounds
        self._sorted = design[order]  # the samples segment by segment
        self.grams = np.zeros((count, design.shape[1], design.shape[1]))
        for g in range(count):
            rows = self._sorted[bounds[g] : bounds[g + 1]]
            self.grams[g] = rows.T @ rows

    def moments(self, lum: np.ndarray) -> np.ndarray:
        """(count, C): each segment's A_g^T I_g for the samples' luminance I (M,)."""
        rows = self._sorted * lum[self._order, None]
        starts = self._bounds[:-1]
        filled = self._bounds[1:] > starts
        out = np.zeros((len(self.grams), self.design.shape[1]))
        if np.any(filled):
            out[filled] = np.add.reduceat(rows, starts[filled], axis=0)
        return out

    def counts(self) -> np.ndarray:
        """(count,): the samples in each segment."""
        return np.diff(self._bounds)

    def __call__(self, segment_albedo: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
        """The Gram matrix for per-segment albedo (count,) and per-sample weights (M,; None:
        every one 1)."""
        gram = np.tensordot(segment_albedo**2, self.grams, axes=1)
        if weights is None:
            return gram
        low = np.flatnonzero(weights < 1.0)
        if len(low):
            rows = self.design[low]
            scale = (weights[low] - 1.0) * segment_albedo[self.labels[low]] ** 2
            gram += rows.T @ (rows * scale[:, None])
        return gram


def _solve_weighted(
    design: np.ndarray,
    gram: np.ndarray,
    rhs_weights: np.ndarray,
    bands: int,
    regularization: float,
    with_bounce: bool,
    prior: np.ndarray | None,
) -> tuple[np.ndarray, float]:
    """The normal equations of `solve_regularised` from A = `design`: (A^T diag(g) A) x =
    A^T r, `gram` = A^T diag(g) A and r = rhs_weights (a model I = a (T l + beta B) with
    robust weights w has g = w a^2, r = w a I: SegmentGrams). beta < 0 (more bounce than
    the data supports): the light alone is solved, from the same matrices."""
    full = penalty_matrix(bands, regularization, prior, with_bounce)
    return _solve_normal(gram, design.T @ rhs_weights, bands, full, with_bounce)


def _solve_normal(
    gram: np.ndarray, rhs: np.ndarray, bands: int, full: np.ndarray, with_bounce: bool
) -> tuple[np.ndarray, float]:
    """`_solve_weighted` from its normal equations' two sides, gram (C, C) and rhs (C,), and
    its `penalty_matrix` `full` (C, C)."""
    n = bands * bands
    penalty = full[:n, :n]
    if with_bounce:
        scale = float(np.mean(np.diag(gram))) or 1.0
        x = np.linalg.solve(gram + scale * full, rhs)
        if x[-1] >= 0.0:
            return x[:n], float(x[-1])
    scale = float(np.mean(np.diag(gram)[:n])) or 1.0
    return np.linalg.solve(gram[:n, :n] + scale * penalty, rhs[:n]), 0.0


def estimate_light(
    transfer: np.ndarray,
    color_linear: np.ndarray,
    params: EstimationParams,
    segments: np.ndarray | None = None,
    bounce: np.ndarray | None = None,
    up: np.ndarray | None = None,
    below_horizon_unseen: bool = False,
    *,
    seed: int = 0,
    checkpoint: Callable[[], None] | None = None,
    clipped_fraction: float | None = None,
) -> LightEstimate:
    """Solve T l = I_c for the distant light (section 5.2, made robust: module docstring).

    transfer: (M, C) SH transfer per pixel, C = L*L for L bands (as many are solved for, or
    fewer when the normals cannot constrain them); color_linear: (M, 3) linear RGB of those
    pixels; seed: of the random subset when more than params.light_max_samples are usable;
    segments: optional (M,) integer material label per pixel. With labels, each material
    gets its own unknown albedo a_g and the model is I = a_g T l, solved by alternating
    between l and the a_g (the paper assumes one grey albedo everywhere).
    bounce: optional (M,) one-bounce light of the occluders per pixel (in the luminance
    units of the image); the model is then I = a_g (T l + beta B) with beta >= 0 solved too.
    up: optional unit "up" vector (frame of T), the normal of the surface the scene stands
    on: light from below its horizon cannot reach the scene directly, so its radiance is
    damped with weight `params.horizon_prior` (nothing visible constrains it otherwise):
    always when `below_horizon_unseen` (the transfer gave no pixel a direction below that
    horizon), else only when the unconstrained fit puts the light there.
    Returns an estimate with zero coefficients and confidence 0 when too few usable pixels
    (Confidence.reason says why, as it does whenever the confidence is low).
    checkpoint: optional, called before each robust iteration; whatever it raises ends the
    fit there (a server's per-frame deadline).
    clipped_fraction: the share of the scene's pixels that are clipped, when the caller
    chose the pixels among unclipped ones (`fittable_colour`); else the share among these.
    """
    t = np.asarray(transfer)  # float64 only for the rows used (below): exact either way
    if not np.issubdtype(t.dtype, np.floating):
        t = t.astype(np.float64)
    n_coeffs = t.shape[-1]
    samples = _usable_samples(
        t.reshape(-1, n_coeffs), color_linear, bounce, segments, params.light_max_samples, seed
    )
    t, lum, rgb, b, labels = (
        samples.transfer,
        samples.lum,
        samples.rgb,
        samples.bounce,
        samples.labels,
    )
    if len(lum) < params.min_samples:
        return LightEstimate(
            np.zeros(n_coeffs),
            Confidence(
                samples=len(lum),
                reason=f"{len(lum)} usable pixels < min_samples "
                f"{params.min_samples} ({samples.left_out})",
            ),
            np.zeros((3, n_coeffs)) if params.estimate_rgb else None,
        )

    max_bands = math.isqrt(n_coeffs)
    bands, cond = choose_bands(t, max_bands)
    fit, prior = _fit_light(t, lum, b, labels, bands, params, up, below_horizon_unseen, checkpoint)
    pred = fit.albedo * fit.shading
    residual = float(
        np.sqrt(np.average(((pred - lum) / np.maximum(lum, DARK_LEVEL)) ** 2, weights=fit.weights))
    )
    full = np.zeros(n_coeffs)
    full[: bands * bands] = fit.coeffs
    sh_rgb = None
    if params.estimate_rgb:
        sh_rgb = np.zeros((3, n_coeffs))
        for ch in range(3):
            sh_rgb[ch, : bands * bands] = solve_regularised(
                t * fit.albedo[:, None],
                rgb[:, ch],
                fit.weights,
                bands,
                params.regularization,
                None if b is None else b * fit.albedo,
                prior,
            )[0]
    evidence = FitEvidence(
        len(lum),
        cond,
        bands,
        normal_spread(t),
        horizon_disagreement_deg(full, up),
        residual,
        samples.clipped_fraction if clipped_fraction is None else clipped_fraction,
    )
    value = confidence_value(evidence)
    reason = low_confidence_reason(evidence, max_bands, value)
    return LightEstimate(
        full,
        Confidence(
            len(lum), cond, bands, value, reason, evidence.normal_spread, evidence.horizon_deg
        ),
        sh_rgb,
        residual,
        fit.beta,
        prior is not None,
        FitState(
            samples.rows if samples.rows is not None else np.arange(len(lum)),
            fit.design,
            fit.albedo,
            fit.weights,
            lum,
            rgb,
            penalty_matrix(bands, params.regularization, prior, b is not None),
            bands,
        ),
    )


def normal_spread(transfer: np.ndarray) -> float:
    """How many directions the observed surfaces face: 1 - |mean unit n|^2 over the pixels,
    n the band-1 part of each transfer vector (its visibility-weighted bent normal). 0 for
    one plane (the light's direction is not observable from its shading), 2/3 for normals
    spread evenly over a hemisphere, 1 for a closed object seen from everywhere; 0 without
    band 1 (nothing then says where the surfaces face)."""
    n = np.asarray(transfer)[:, 1:4]
    if n.shape[1] < 3 or not len(n):
        return 0.0
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return float(np.clip(1.0 - np.sum(np.mean(n, axis=0) ** 2), 0.0, 1.0))


def horizon_disagreement_deg(coeffs: np.ndarray, up: np.ndarray | None) -> float:
    """Degrees between the whole-sphere dominant direction of `coeffs` and the direction
    of its light above the horizon of `up` (sh.above_horizon_direction, the one reported):
    large when much of the estimated light lies below the horizon of the surface the scene
    stands on, light that cannot reach it (the ground's glow, or light the normals leave
    unconstrained), so that the reported direction rests on taking that light out.
    0 without a support plane (`up` None) or without a direction."""
    if up is None:
        return 0.0
    whole = sh.dominant_direction(coeffs)
    upper = sh.above_horizon_direction(coeffs, np.asarray(up, np.float64))
    if not (np.any(whole) and np.any(upper)):
        return 0.0
    return float(np.degrees(np.arccos(np.clip(whole @ upper, -1.0, 1.0))))


@dataclass
class _Samples:
    """The pixels a fit uses (usable, randomly sub-sampled above the limit)."""

    transfer: np.ndarray  # (M, C) float64 (converted after the subset is chosen)
    lum: np.ndarray  # (M,) linear luminance
    rgb: np.ndarray  # (M, 3) linear RGB
    bounce: np.ndarray | None  # (M,)
    labels: np.ndarray | None  # (M,) segment index 0..G-1
    left_out: str  # why the others were not used, e.g. "10 clipped, 3 too dark"
    clipped_fraction: float = 0.0  # of the pixels with transfer: bright emitters, highlights
    rows: np.ndarray | None = None  # (M,) indices of these pixels among the inputs' rows


def _colour_tests(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per row of linear RGB (N, 3): luminance, finite, clipped, too dark."""
    lum = rgb @ LUMA.astype(rgb.dtype, copy=False)
    with np.errstate(invalid="ignore"):
        return lum, np.isfinite(lum), channel_max(rgb) >= CLIP_LEVEL, ~(lum > DARK_LEVEL)


def fittable_colour(color_linear: np.ndarray, among: np.ndarray) -> tuple[np.ndarray, float]:
    """Which pixels of a linear image (H, W, 3) the fit may use by their colour alone (finite,
    neither clipped nor near-black), (H, W) bool, and the share of the pixels `among` (H, W)
    bool that are clipped (for the confidence's reason: emitters, highlights)."""
    rgb = np.asarray(color_linear).reshape(-1, 3)
    _, finite, clipped, dark = _colour_tests(rgb)
    usable = (finite & ~clipped & ~dark).reshape(color_linear.shape[:2])
    counted = np.asarray(among).reshape(-1)
    share = float(clipped[counted].mean()) if counted.any() else 0.0
    return usable, share


def _usable_samples(
    t: np.ndarray,
    color_linear: np.ndarray,
    bounce: np.ndarray | None,
    segments: np.ndarray | None,
    max_samples: int,
    seed: int,
) -> _Samples:
    """Clipped, near-black, non-finite and transfer-less pixels left out; above
    max_samples a seeded random subset (neighbouring pixels repeat each other).

    The tests run in the inputs' own precision over every pixel; only the rows kept are
    converted to float64 (the fit's precision)."""
    rgb_all = np.asarray(color_linear).reshape(-1, 3)
    lum_all, finite, clipped, dark = _colour_tests(rgb_all)
    with np.errstate(invalid="ignore"):
        finite &= np.isfinite(t).all(axis=1)
        no_transfer = ~(t[:, 0] > 1e-6)
    usable = finite & ~clipped & ~dark & ~no_transfer
    keep = np.flatnonzero(usable)
    if len(keep) > max_samples:
        rng = np.random.default_rng(seed)
        keep = np.sort(rng.choice(keep, max_samples, replace=False))
    b = None if bounce is None else np.asarray(bounce, dtype=np.float64).reshape(-1)[keep]
    labels = None
    if segments is not None:
        _, labels = np.unique(np.asarray(segments).reshape(-1)[keep], return_inverse=True)
    left_out = (
        f"of {len(lum_all)}: {int(clipped.sum())} clipped, {int(dark.sum())} too "
        f"dark, {int(no_transfer.sum())} without transfer, "
        f"{int((~finite).sum())} not finite"
    )
    rgb = rgb_all[keep].astype(np.float64)
    with_transfer = int((~no_transfer).sum())
    clipped_fraction = float((clipped & ~no_transfer).sum()) / max(with_transfer, 1)
    return _Samples(
        t[keep].astype(np.float64), rgb @ LUMA, rgb, b, labels, left_out, clipped_fraction, keep
    )


def _fit_light(
    t: np.ndarray,
    lum: np.ndarray,
    b: np.ndarray | None,
    labels: np.ndarray | None,
    bands: int,
    params: EstimationParams,
    up: np.ndarray | None,
    below_horizon_unseen: bool,
    checkpoint: Callable[[], None] | None = None,
) -> tuple[_Fit, np.ndarray | None]:
    """The robust fit, with the below-horizon prior where it applies; (fit, prior or None)."""
    learned = _learned_prior(params, up, bands)
    use_prior = up is not None and params.horizon_prior > 0
    if not (use_prior and below_horizon_unseen):
        fit = _alternate(t, lum, b, labels, bands, params, learned, checkpoint)
        # the data put the light below the horizon of the surface the scene stands on:
        # light from there cannot reach the scene, so that lobe is an artefact of what the
        # normals leave unconstrained; fit again with below-horizon radiance held to a
        # ground's glow
        use_prior = use_prior and float(sh.dominant_direction(fit.coeffs) @ up) < 0.0
        if not use_prior:
            return fit, learned
    assert up is not None  # use_prior implies it
    # built only when used: it costs a 2048-direction SH evaluation
    prior = params.horizon_prior * below_horizon_gram(up, bands, params.horizon_ground_albedo)
    if learned is not None:
        prior = prior + learned
    return _alternate(t, lum, b, labels, bands, params, prior, checkpoint), prior


def _learned_prior(
    params: EstimationParams, up: np.ndarray | None, bands: int
) -> np.ndarray | None:
    """params.light_prior times the prior learned from HDR maps, in the frame where `up` is
    up (pipeline.light_prior); None when off or without a support plane."""
    if params.light_prior <= 0 or up is None:
        return None
    from arlight.pipeline.light_prior import prior_matrix

    exclude = frozenset(n.strip() for n in params.light_prior_exclude.split(",") if n.strip())
    return params.light_prior * prior_matrix(np.asarray(up, np.float64), bands, exclude)


@dataclass
class _Fit:
    coeffs: np.ndarray
    beta: float
    albedo: np.ndarray  # per sample, sample-weighted mean 1
    weights: np.ndarray  # robust weights per sample
    shading: np.ndarray  # T l + beta B per sample
    design: np.ndarray  # the columns [T | B] the fit solved with (reused, not rebuilt)


def _alternate(
    t: np.ndarray,
    lum: np.ndarray,
    b: np.ndarray | None,
    labels: np.ndarray | None,
    bands: int,
    params: EstimationParams,
    prior: np.ndarray | None,
    checkpoint: Callable[[], None] | None = None,
) -> _Fit:
    """Regularised solve, then `robust_iterations` rounds of per-segment albedo (and, with
    `robust_threshold` > 0, Huber re-weighting of relative residuals), each followed by a
    new solve."""
    n = bands * bands
    design = _design(t, bands, b)
    weights = np.ones(len(lum))
    albedo = np.ones(len(lum))
    grams = SegmentGrams(design, labels)
    segment_albedo = np.ones(len(grams.grams))

    def solve() -> tuple[np.ndarray, float]:
        return _solve_weighted(
            design,
            grams(segment_albedo, weights),
            weights * albedo * lum,
            bands,
            params.regularization,
            b is not None,
            prior,
        )

    def shading() -> np.ndarray:
        s = design[:, :n] @ coeffs
        return s + beta * b if b is not None else s

    coeffs, beta = solve()
    if labels is None and params.robust_threshold <= 0.0:
        return _Fit(coeffs, beta, albedo, weights, shading(), design)  # nothing to alternate
    if params.robust_threshold <= 0.0:
        # without re-weighting each pass needs only the segments' sums (the same sums as
        # over the samples, to rounding): a pass costs microseconds, not milliseconds
        moments, counts = grams.moments(lum), grams.counts()
        penalty = penalty_matrix(bands, params.regularization, prior, b is not None)
        for _ in range(params.robust_iterations):
            if checkpoint is not None:
                checkpoint()
            x = coeffs if b is None else np.append(coeffs, beta)
            num = moments @ x
            den = np.einsum("i,gij,j->g", x, grams.grams, x)
            segment_albedo = _normalised_albedo(num, den, counts)
            coeffs, beta = _solve_normal(
                grams(segment_albedo, None),
                segment_albedo @ moments,
                bands,
                penalty,
                b is not None,
            )
        return _Fit(coeffs, beta, segment_albedo[labels], weights, shading(), design)
    for _ in range(params.robust_iterations):
        if checkpoint is not None:
            checkpoint()
        shade = shading()
        if labels is not None:
            albedo, segment_albedo = _segment_albedo(shade, lum, labels, weights)
        if params.robust_threshold > 0.0:
            # relative to the prediction, not the observation: a wrongly bright patch then
            # has a large residual and a correct dark pixel a small one
            pred = albedo * shade
            rel = (pred - lum) / np.maximum(pred, DARK_LEVEL)
            sigma = 1.4826 * np.median(np.abs(rel - np.median(rel))) + 1e-6
            a = np.abs(rel) / (params.robust_threshold * sigma)
            weights = np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))  # Huber
        coeffs, beta = solve()
    return _Fit(coeffs, beta, albedo, weights, shading(), design)


def _segment_albedo(
    shading: np.ndarray, lum: np.ndarray, labels: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(per-pixel, per-segment) albedo, a_g = argmin sum_g w (a_g s - I)^2, normalised so
    the sample-weighted mean is 1 (the light keeps the overall scale)."""
    n = labels.max() + 1
    num = np.bincount(labels, weights * shading * lum, minlength=n)
    den = np.bincount(labels, weights * shading * shading, minlength=n)
    a = _normalised_albedo(num, den, np.bincount(labels, minlength=n))
    return a[labels], a


def _normalised_albedo(num: np.ndarray, den: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(count,) per-segment albedo num / den (sum w s I / sum w s^2; 1 where den is 0),
    at least 1e-3, normalised so that its mean over the samples (`counts` per segment) is 1."""
    a = np.where(den > 1e-12, num / np.maximum(den, 1e-12), 1.0)
    a = np.clip(a, 1e-3, None)
    return a / max(float(counts @ a) / max(int(counts.sum()), 1), 1e-6)
