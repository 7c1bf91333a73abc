"""Motion model fit for the yaw labeler (resim/labeling/flow.py, step 3): flow samples -> rotation per frame pair.

Per chunk of pairs, batched: the joint (yaw, pitch, roll, FOE) fit of each pair by Gauss-Newton + IRLS
(``_fit_motion``), then the FOE's x placed by the car's kinematics: pooled over the video (``_pool_add``,
``_pool_params``, ``_fit_pooled``; unknown rig, the default) or from the known rig (``_fit_rig``,
``_distance_over_height``). The model and why it is fitted this way: resim/labeling/flow.py's docstring and
docs/labeling.md. ``MotionFit`` is a mixin of ``FlowLabeler``: it uses the labeler's ``flow_cfg`` and per-video state
(``_fps_hz``, ``_results``, ``_dhs``, ``_straight``, ``_pool``, ``_pending``, ``last_foe_model``: ``_start_video``).
"""
from __future__ import annotations

import math

import numpy as np

from resim.labeling.flow_sampling import _PairData


class MotionFit:
    """Per-chunk fits of the motion model (``_solve_chunk``) and the video's pooled FOE statistics."""

    @staticmethod
    def _translation(fields, U, V, theta):
        """Flow left after the rotation theta (P, 3): (Tu, Tv), radial from the FOE for static points."""
        (Au, Av), (Bu, Bv), (Cu, Cv) = fields
        return (U - (Au * theta[:, 0:1] + Bu * theta[:, 1:2] + Cu * theta[:, 2:3]),
                V - (Av * theta[:, 0:1] + Bv * theta[:, 1:2] + Cv * theta[:, 2:3]))

    @staticmethod
    def _rot_fields(x, y, f):
        A = (f + x * x / f, x * y / f)
        B = (x * y / f, f + y * y / f)
        C = (-y, x)
        return A, B, C

    def _fit_motion(self, X, Y, U, V, W0, e0, f, n_grid, free_foe: bool = True, w_start=None, iters=None):
        """Batched joint fit of (yaw, pitch, roll) and a focus of expansion *per pair*. Arrays (P, N).

        W0 = 0 where padded; e0 (2,) or (P, 2) is the prior FOE (px from the image centre); with
        ``free_foe=False`` the FOE is held at e0 and only the rotation is fitted (known rig, ``_fit_rig``).
        The rotation-only residual cross(flow - R theta, p - e) / |p - e| is zero for every static point
        (translation is radial from e); linearised in the FOE shift de around the current (theta, e):

            cross(flow, p - e) = theta . cross(R, p - e) + cross(T, de),   T = flow - R theta

        a 5-parameter linear least-squares problem per pair, solved by Gauss-Newton + IRLS (Cauchy).
        The FOE must be free per pair: a car turns on an arc, so between two frames the camera moves
        along the chord (rotated by half the yaw step) and, with the camera ahead of the rear axle, also
        sideways by (lever arm x yaw): the FOE shifts towards the turn by f (dt/2 + L/v) yaw_rate. A FOE
        held fixed turns that shift into a yaw bias of (d/2 + L) / Z (5-15 % on the road, measured).
        Where the car barely moves (|T| small) the FOE columns vanish and the prior keeps e near e0.

        ``w_start`` (P, N) starts the IRLS from earlier weights (a re-fit), ``iters`` overrides the number of steps.

        Returns theta (P, 3) rad, foe (P, 2) px, kept (P,) share of the grid kept as inliers,
        info (P,) weight of the FOE evidence (0 = none), w (P, N) the final IRLS weights.
        """
        fc = self.flow_cfg
        P, N = X.shape
        valid = W0 > 0
        # the five design columns are kept as separate (P, N) arrays: stacking them as (P, N, 5) cost ~1.5x
        # the time in temporaries (same numbers to 1e-16)
        fields = self._rot_fields(X, Y, f)
        (Au, Av), (Bu, Bv), (Cu, Cv) = fields     # yaw, pitch, roll fields
        e = np.broadcast_to(np.asarray(e0, np.float64), (P, 2)).copy()
        e0a = np.broadcast_to(np.asarray(e0, np.float64), (P, 2))
        theta = np.zeros((P, 3))
        reg = np.array([1e-6, 1e-6, 1e-6 / f ** 2, 0.0, 0.0]) * f * f
        diag = np.arange(5)
        pad = np.where(np.arange(N) % 2 == 0, 0.0, np.inf)[None, :]
        lim = 0.5 * f     # the FOE of a forward camera stays well inside the frame
        w = W0 if w_start is None else w_start
        n_it = fc.irls_iters + fc.foe_iters if iters is None else iters   # the same with the FOE held (known rig)
        for it in range(n_it):
            dx, dy = X - e[:, :1], Y - e[:, 1:]
            ir = 1.0 / np.maximum(np.hypot(dx, dy), 0.05 * f)
            dxr, dyr = dx * ir, dy * ir
            cols = [Au * dyr - Av * dxr, Bu * dyr - Bv * dxr, Cu * dyr - Cv * dxr]    # cross(R, p - e) / |p - e|
            b = U * dyr - V * dxr
            if it > 0 and free_foe:   # the first step is rotation only: no translation to linearise the FOE around
                Tu, Tv = self._translation(fields, U, V, theta)
                cols += [-Tv * ir, Tu * ir]
            k = len(cols)
            H = np.zeros((P, 5, 5))
            rhs = np.zeros((P, 5))
            for i in range(k):
                wc = cols[i] * w
                rhs[:, i] = np.einsum("pn,pn->p", wc, b)
                for j in range(i, k):
                    H[:, i, j] = H[:, j, i] = np.einsum("pn,pn->p", wc, cols[j])
            sw = np.maximum(w.sum(1), 1.0)
            lam = fc.foe_prior * sw
            H[:, diag, diag] += reg[None, :] * sw[:, None]
            H[:, 3, 3] += lam + 1e-12
            H[:, 4, 4] += lam + 1e-12
            rhs[:, 3:] += lam[:, None] * (e0a - e)
            sol = np.linalg.solve(H, rhs[..., None])[..., 0]
            theta = sol[:, :3]
            info = H[:, 3, 3] - lam
            res = b - sum(cols[i] * sol[:, i:i + 1] for i in range(k))
            if k == 5:
                e = np.clip(e + sol[:, 3:], -lim, lim)
            # median |res| over the valid points of each pair: padding alternates 0 and +inf, which
            # leaves the median in place (to within one pad) and keeps np.median's fast partition
            med = np.median(np.where(valid, np.abs(res), pad), axis=1)
            scale = np.maximum(1.4826 * np.where(np.isfinite(med), med, 0.0), fc.robust_scale_px)[:, None]
            w = W0 / (1.0 + (res / (2.0 * scale)) ** 2)    # Cauchy
        few = valid.sum(1) < 8
        theta[few] = 0.0
        e[few] = e0a[few]
        kept = (valid & (np.abs(res) < 3.0 * scale)).sum(1) / max(n_grid, 1)
        kept[few] = 0.0
        info = np.where(few, 0.0, info / np.maximum(w.sum(1), 1.0))
        return theta, e, kept, info, w

    def _distance_over_height(self, X, Y, U, V, W0, w, theta, e, f):
        """Distance driven per pair over the camera height, d / h, from the ground-plane flow. (P,), nan = unknown.

        A ground point seen at y rows below the horizon (which passes through the FOE) lies at depth
        Z = f h / (y - e_y). Moving d closer, it is seen at e + (p - e) Z / (Z - d): its translational flow
        has the radial rate s_p = d / (Z - d) (not d / Z: at 3-5 m and 0.8 m per pair that is 20-35 % more),
        so d / h = f s_p / ((1 + s_p) (y - e_y)). Median over the fit's inliers well below the horizon
        (objects standing on the road are nearer than the ground behind them and read high; the median
        shrugs off a few).
        """
        Tu, Tv = self._translation(self._rot_fields(X, Y, f), U, V, theta)
        dx, dy = X - e[:, :1], Y - e[:, 1:]
        r2 = dx * dx + dy * dy
        ground = (W0 > 0) & (w > 0.5 * W0) & (dy > 0.08 * f) & (r2 > (0.1 * f) ** 2)
        sp = (Tu * dx + Tv * dy) / np.where(ground, r2, 1.0)
        ratio = np.where(ground, f * sp / np.where(ground, (1.0 + sp) * dy, 1.0), np.nan)
        out = np.full(len(theta), np.nan)
        enough = ground.sum(1) >= 10
        if enough.any():
            out[enough] = np.nanmedian(ratio[enough], axis=1)
        return out

    def _pool_add(self, theta, e, info) -> None:
        """Unknown rig, pooled FOE model: add one chunk's per-pair fit to the video's statistics.

        A car turns about its rear axle, so the FOE sits at e_x = a - f k yaw per pair (``_fit_rig``):
        a is the FOE of straight driving (the camera's mount yaw; fixed for a video), k = 1/2 + L/d
        (chord + lever arm over distance per pair; changes slowly with speed). Neither is known for
        OpenDV, but both are shared by many pairs, while the per-pair fit lets flow errors trade yaw
        against e_x pair by pair. a = evidence-weighted median of the per-pair FOE over the video's straight
        pairs (the last ``foe_straight_pool_pairs`` of them), those whose yaw rate averaged over +-0.5 s is below ``straight_yaw_deg_s`` (one pair's rate is
        too noisy to tell: +-1-3 deg/s on the tests' renderer). On the synthetic world a from all pairs was off
        by up to 8 px (turns pull it), from straight pairs by a median 0.5 px; a yaw bias per pair of
        (d / Z) (delta a / f) is 5 deg per 4 s at 2 deg of mount yaw
        (docs/lab/2026-11-22-labeler-calibration.md, "Fifth look").
        k = weighted least squares of (a - e_x) on f yaw over the last ``foe_pool_pairs`` pairs.
        """
        fc = self.flow_cfg
        good = info > 1e-4
        yaw = theta[:, 0]
        lim = math.radians(fc.straight_yaw_deg_s / self._fps_hz)
        smooth = _running_mean(yaw, max(1, int(round(0.5 * self._fps_hz))))
        straight = good & (np.abs(smooth) < lim)
        self._straight.append((e[straight, 0], info[straight]))
        self._pool.append((e[:, 0], yaw, np.where(good, info, 0.0)))
        # keep only what the trailing pools need: a is re-estimated every chunk, and over a video of hours a median
        # over every straight pair seen would grow the per-chunk cost without bound (8 ms per chunk at 100k pairs)
        while sum(len(s_[0]) for s_ in self._straight[1:]) >= fc.foe_straight_pool_pairs:
            self._straight.pop(0)
        while sum(len(p_[0]) for p_ in self._pool[1:]) >= fc.foe_pool_pairs:
            self._pool.pop(0)

    def _pool_params(self, f: float) -> tuple[float, float] | None:
        """(a px, k) of the pooled FOE model, or None while less than ``foe_min_straight_s`` of straight
        driving has been seen (a short clip all in one curve has no FOE of straight driving to pool)."""
        fc = self.flow_cfg
        sx = np.concatenate([s_[0] for s_ in self._straight])
        if len(sx) < max(3, fc.foe_min_straight_s * self._fps_hz):
            return None
        a = _wmedian(sx, np.concatenate([s_[1] for s_ in self._straight]))
        ex, yw, iw = (np.concatenate([p_[i] for p_ in self._pool])[-fc.foe_pool_pairs:] for i in range(3))
        den = float(np.sum(iw * (f * yw) ** 2))
        k = float(np.clip(np.sum(iw * (a - ex) * f * yw) / den, 0.0, fc.foe_k_max)) if den > 0 else 0.5
        return a, k

    def _fit_pooled(self, X, Y, U, V, W0, theta, e, info, w, f, n_grid, a, k):
        """Rotation-only re-fit with the FOE at (a - f k yaw, e_y pooled over the chunk), twice (the FOE
        follows the re-fitted yaw), each two IRLS steps from the per-pair fit's weights ``w`` (on the synthetic
        world as good as five steps from scratch, at 40 % of the CPU). Returns (theta, FOE, kept)."""
        lim = 0.5 * f
        E = np.empty_like(e)
        E[:, 1] = _chunk_foe_y(e, info)
        kept = None
        for _ in range(2):
            E[:, 0] = np.clip(a - f * k * theta[:, 0], -lim, lim)
            theta, _, kept, _, w = self._fit_motion(X, Y, U, V, W0, E, f, n_grid, free_foe=False, w_start=w, iters=2)
        return theta, E, kept

    def _fit_rig(self, X, Y, U, V, W0, theta, e, info, w, f, n_grid):
        """Known rig: the FOE's x follows the car's kinematics instead of being fitted per pair.

        A car turns about its rear axle; between two samples a camera ``camera_ahead_m`` = L ahead of it
        moves along the chord (half a yaw step into the turn) and sideways by L x yaw, so the FOE sits at
        e_x = -f yaw (1/2 + L / d) (camera looking along the car's axis), d = distance per pair, from the
        ground-plane flow and ``camera_height_m`` (``_distance_over_height``, smoothed over +-5 pairs).
        e_y (the camera's pitch) is pooled over the chunk. Then rotation only is fitted with that FOE,
        ``rig_iters`` times. Per-pair FOE freedom is what lets flow errors trade yaw against e_x (the
        remaining error of the unknown-rig fit, docs/labeling.md); with the FOE fixed by the rig they cannot.
        """
        fc = self.flow_cfg
        P = len(theta)
        ey = _chunk_foe_y(e, info)
        lam = fc.camera_ahead_m / fc.camera_height_m
        lim = 0.5 * f
        E = e.copy()
        E[:, 1] = ey
        kept = None
        sm = np.full(P, np.nan)
        for _ in range(fc.rig_iters):
            dh = self._distance_over_height(X, Y, U, V, W0, w, theta, E, f)
            if not np.isfinite(dh).any():
                break                      # no ground seen: keep the free-FOE fit
            sm = _running_nanmedian(dh, 5)
            sm = np.where(np.isfinite(sm), sm, np.nanmedian(dh))
            k = 0.5 + lam / np.maximum(sm, 1e-3)
            E[:, 0] = np.clip(-f * theta[:, 0] * k, -lim, lim)
            theta, _, kept, _, w = self._fit_motion(X, Y, U, V, W0, E, f, n_grid, free_foe=False)
        self._dhs.append(sm)
        return theta, E, kept

    def _solve_chunk(self, pairs: list[_PairData], n_grid: int, f: float, e0: tuple[float, float]):
        """Fit one chunk; its result goes to ``self._results`` (now, or later for a deferred pooled chunk).

        Returns the next chunk's FOE prior: the evidence-weighted median FOE of this one's per-pair fit."""
        X, Y, U, V, W0 = self._stack(pairs)
        theta, e, kept, info, w = self._fit_motion(X, Y, U, V, W0, e0, f, n_grid)
        idx = len(self._results)
        self._results.append((theta[:, 0].copy(), kept, e, "per_pair"))      # the free per-pair fit
        rig_ok = False
        if self.flow_cfg.camera_ahead_m is not None:
            # known rig: the FOE follows the kinematics; the running prior below stays the free fit's
            theta_r, e_r, kept_r = self._fit_rig(X, Y, U, V, W0, theta, e, info, w, f, n_grid)
            if kept_r is not None:
                self._results[idx] = (theta_r[:, 0].copy(), kept_r, e_r, "rig")
                rig_ok = True
        else:
            self._dhs.append(np.full(len(pairs), np.nan))
        if not rig_ok and self.flow_cfg.foe_model == "pooled":     # a known rig without visible ground lands here
            self._pool_add(theta, e, info)
            self._pending.append((idx, X, Y, U, V, W0, theta, e, info, w))
            params = self._pool_params(f)
            if params is not None:
                # chunks seen before enough straight driving get the model too (labels are returned at the end)
                for j, *arrays in self._pending:
                    th_p, e_p, kept_p = self._fit_pooled(*arrays, f, n_grid, *params)
                    self._results[j] = (th_p[:, 0].copy(), kept_p, e_p, "pooled")
                self._pending = []
                self.last_foe_model = params
            elif len(self._pending) > _MAX_PENDING_CHUNKS:
                self._pending.pop(0)                       # memory bound: the oldest keeps its per-pair fit
        # the next chunk's prior: the evidence-weighted median FOE of this one (the camera is fixed to the
        # car, so the FOE of straight driving is stable; turns shift it both ways and average out)
        good = info > 1e-4
        if good.sum() >= 3:
            e0 = (_wmedian(e[good, 0], info[good]), _wmedian(e[good, 1], info[good]))
        return e0


# pooled FOE model: chunks (60 pairs, ~4 MB of flow samples and weights each) are held back until enough straight
# driving has been seen to place their FOE; beyond this many the oldest keeps its per-pair fit (10 = 60 s at 10 Hz)
_MAX_PENDING_CHUNKS = 10


def _running_nanmedian(x: np.ndarray, half: int) -> np.ndarray:
    """Median of the finite values of x[i - half : i + half + 1] for every i (nan where there are none)."""
    padded = np.pad(x, half, constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)      # (len(x), 2 half + 1)
    out = np.full(len(x), np.nan)
    some = np.isfinite(win).any(1)
    out[some] = np.nanmedian(win[some], axis=1)
    return out


def _running_mean(x: np.ndarray, half: int) -> np.ndarray:
    """Mean of x[i - half : i + half + 1] (cut at the ends) for every i."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    i = np.arange(len(x))
    lo, hi = np.maximum(i - half, 0), np.minimum(i + half + 1, len(x))
    return (c[hi] - c[lo]) / (hi - lo)


def _chunk_foe_y(e: np.ndarray, info: np.ndarray) -> float:
    """The FOE's y (the camera's pitch) pooled over a chunk: evidence-weighted median of the per-pair fit's."""
    good = info > 1e-4
    return _wmedian(e[good, 1], info[good]) if good.sum() >= 3 else float(np.median(e[:, 1]))


def _wmedian(x: np.ndarray, w: np.ndarray) -> float:
    o = np.argsort(x)
    c = np.cumsum(w[o])
    return float(x[o][np.searchsorted(c, 0.5 * c[-1])])
