"""Batched, vectorised minimal pose solvers in torch: P3P (Grunert) and 4-point hypotheses (P3P + the 4th
point choosing among the solutions). No Python loop per hypothesis; works on any device. Use float64.

P3P follows Grunert's solution as reviewed by Haralick, Lee, Ottenberg and Noelle, "Review and analysis of
solutions of the three point perspective pose estimation problem", IJCV 13(3), 1994: with the distances
s1, s2, s3 of the three points along their unit bearing vectors and u = s2 / s1, v = s3 / s1, the law of
cosines gives a quartic in v (coefficients A4..A0 of :func:`grunert_quartic`). Its real roots are found
with a closed-form (Ferrari) quartic solver in real arithmetic, polished by Newton steps
(:func:`solve_quartic`; complex tensors and batched ``torch.linalg.eigvals`` of companion matrices were
5-10x slower on the CPU); each root gives u, s1 and the three camera-frame points, and the rotation
follows from the triad (orthonormal frame) of the three points in both frames, which is exact for the
congruent triangles P3P produces. Conventions as in :mod:`surftrack.geometry.camera`: x_cam = R x + t.
"""

from __future__ import annotations

import math

import torch


def solve_quartic(coeffs: torch.Tensor, real_tol: float = 1e-3,
                  newton_steps: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Real roots of a4 x^4 + a3 x^3 + a2 x^2 + a1 x + a0 for coefficients (..., 5) = [a4, a3, a2, a1, a0].

    Returns (roots (..., 4), real (..., 4) bool). Real arithmetic only (fast on every device): Ferrari's
    method with the largest real root m of the resolvent cubic, which is >= 0 (the resolvent is -q^2 <= 0
    at 0), so the quartic splits into two quadratics with real coefficients. A quadratic whose
    discriminant is slightly negative has a complex pair with imaginary part below ``real_tol`` x
    (1 + |real part|): it is kept as a (double) real root, as noisy P3P needs. Roots are polished by
    ``newton_steps`` Newton steps. A nearly biquadratic quartic (m ~ 0) is solved as a quadratic in y^2.
    Not a quartic (a4 relatively 0, non-finite coefficients): no roots.
    """
    c = coeffs.to(torch.float64)
    scale = c.abs().amax(-1)
    ok = torch.isfinite(c).all(-1) & (c[..., 0].abs() > 1e-12 * scale) & (scale > 0)
    a4 = torch.where(ok, c[..., 0], torch.ones_like(c[..., 0]))
    b, cc, d, e = (torch.where(ok, c[..., k], torch.zeros_like(a4)) / a4 for k in range(1, 5))
    # Depressed quartic y^4 + p y^2 + q y + r with x = y - b / 4.
    b2 = b * b
    p = cc - 3.0 * b2 / 8.0
    q = d - b * cc / 2.0 + b2 * b / 8.0
    r = e - b * d / 4.0 + b2 * cc / 16.0 - 3.0 * b2 * b2 / 256.0
    # Resolvent cubic g(m) = m^3 + p m^2 + (p^2/4 - r) m - q^2/8; its largest real root, via m = z - p/3.
    P = -p * p / 12.0 - r
    Q = -p * p * p / 108.0 + p * r / 3.0 - q * q / 8.0
    disc = Q * Q / 4.0 + P * P * P / 27.0
    sd = torch.sqrt(disc.clamp(min=0.0))
    z_one = _cbrt(-Q / 2.0 + sd) + _cbrt(-Q / 2.0 - sd)
    Pn = torch.where(P < 0, P, -torch.ones_like(P))
    arg = (1.5 * Q / Pn * torch.sqrt(-3.0 / Pn)).clamp(-1.0, 1.0)
    z_three = 2.0 * torch.sqrt(-Pn / 3.0) * torch.cos(torch.arccos(arg) / 3.0)
    z = torch.where((disc > 0) | (P >= 0), z_one, z_three)
    m = z - p / 3.0
    g1 = p * p / 4.0 - r
    for _ in range(2):  # Newton on the resolvent (Cardano loses digits when the terms cancel)
        gm = ((m + p) * m + g1) * m - q * q / 8.0
        dg = (3.0 * m + 2.0 * p) * m + g1
        m = torch.where(dg.abs() > 1e-300, m - gm / torch.where(dg.abs() > 1e-300, dg, torch.ones_like(dg)), m)
    # Nearly biquadratic (q ~ 0, so m ~ 0 and q / sqrt(2m) loses its digits): y^2 = (-p +- sqrt(p^2 - 4r)) / 2,
    # the small q y term is left to the Newton steps below.
    biq = m <= 1e-8 * (p.abs() + r.abs().sqrt())
    sm = torch.sqrt((2.0 * m).clamp(min=1e-300))
    D = p * p - 4.0 * r
    sD = torch.sqrt(D.clamp(min=0.0))
    roots, real = [], []
    for s in (1.0, -1.0):
        # Ferrari: y^2 - s sm y + (p/2 + m + s q / (2 sm)) = 0
        disc2 = -2.0 * p - 2.0 * m - 2.0 * s * q / sm
        centre = s * sm / 2.0
        keep = disc2 >= -4.0 * real_tol ** 2 * (1.0 + centre.abs()) ** 2
        h = torch.sqrt(disc2.clamp(min=0.0)) / 2.0
        # biquadratic: y^2 = zq, y = +-sqrt(zq)
        zq = (-p + s * sD) / 2.0
        yq = torch.sqrt(zq.clamp(min=0.0))
        keep_q = (D >= -4.0 * real_tol ** 2) & (zq >= -real_tol ** 2)
        roots += [torch.where(biq, yq, centre + h), torch.where(biq, -yq, centre - h)]
        real += [torch.where(biq, keep_q, keep)] * 2
    x = torch.stack(roots, -1) - (b / 4.0)[..., None]
    real = torch.stack(real, -1) & ok[..., None]
    b_, c_, d_, e_ = (v[..., None] for v in (b, cc, d, e))
    for _ in range(newton_steps):
        f = (((x + b_) * x + c_) * x + d_) * x + e_
        df = ((4.0 * x + 3.0 * b_) * x + 2.0 * c_) * x + d_
        step = f / torch.where(df.abs() > 1e-300, df, torch.ones_like(df))
        x = torch.where((df.abs() > 1e-300) & torch.isfinite(step), x - step, x)
    return x, real & torch.isfinite(x)


def _cbrt(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * x.abs().pow(1.0 / 3.0)


def grunert_quartic(a2: torch.Tensor, b2: torch.Tensor, c2: torch.Tensor, ca: torch.Tensor, cb: torch.Tensor,
                    cg: torch.Tensor) -> torch.Tensor:
    """Coefficients (..., 5) [A4..A0] of Grunert's quartic in v = s3 / s1 (Haralick et al. 1994, eq. 9).

    ``a2, b2, c2``: squared side lengths |P2-P3|^2, |P1-P3|^2, |P1-P2|^2; ``ca, cb, cg``: cosines of the
    angles between the bearing vectors (2,3), (1,3) and (1,2)."""
    amc, apc = (a2 - c2) / b2, (a2 + c2) / b2
    A4 = (amc - 1.0) ** 2 - 4.0 * c2 / b2 * ca * ca
    A3 = 4.0 * (amc * (1.0 - amc) * cb - (1.0 - apc) * ca * cg + 2.0 * c2 / b2 * ca * ca * cb)
    A2 = 2.0 * (amc * amc - 1.0 + 2.0 * amc * amc * cb * cb + 2.0 * (b2 - c2) / b2 * ca * ca
                - 4.0 * apc * ca * cb * cg + 2.0 * (b2 - a2) / b2 * cg * cg)
    A1 = 4.0 * (-amc * (1.0 + amc) * cb + 2.0 * a2 / b2 * cg * cg * cb - (1.0 - apc) * ca * cg)
    A0 = (1.0 + amc) ** 2 - 4.0 * a2 / b2 * cg * cg
    return torch.stack([A4, A3, A2, A1, A0], -1)


Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # x, y, z components, each a contiguous tensor


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _dot(a: Vec, b: Vec) -> torch.Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _unit(a: Vec) -> Vec:
    n = torch.sqrt(_dot(a, a)).clamp(min=1e-300)
    return (a[0] / n, a[1] / n, a[2] / n)


def _triad(p1: Vec, p2: Vec, p3: Vec) -> tuple[Vec, Vec, Vec]:
    """Orthonormal frames of triangles: e1 along p1->p2, e3 the normal, e2 = e3 x e1."""
    e1 = _unit(_sub(p2, p1))
    e3 = _unit(_cross(e1, _sub(p3, p1)))
    return e1, _cross(e3, e1), e3


def _soa(x: torch.Tensor) -> list[Vec]:
    """(H, n, 3) -> n points, each (x, y, z) of contiguous (H,) tensors."""
    c = x.permute(1, 2, 0).contiguous()
    return [(c[i, 0], c[i, 1], c[i, 2]) for i in range(c.shape[0])]


def _p3p_soa(j: list[Vec], P: list[Vec], real_tol: float, residual_tol: float):
    """P3P on structure-of-arrays inputs (unit bearings j, model points P; 3 points of (H,) components).
    Returns R as rows of (4, H) tensors [[R00, R01, R02], ...], t (3 x (4, H)) and valid (4, H)."""
    a2, b2, c2 = (_dot(v, v) for v in (_sub(P[1], P[2]), _sub(P[0], P[2]), _sub(P[0], P[1])))
    ca, cb, cg = _dot(j[1], j[2]), _dot(j[0], j[2]), _dot(j[0], j[1])
    b2s = torch.where(b2 > 0, b2, torch.ones_like(b2))
    v, real = solve_quartic(grunert_quartic(a2, b2s, c2, ca, cb, cg), real_tol)
    v, real = v.T.contiguous(), real.T & (b2 > 0)  # (4, H)
    amc = (a2 - c2) / b2s
    den = 2.0 * (cg - v * ca)
    den = torch.where(den.abs() > 1e-12, den, torch.full_like(den, 1e-12))
    u = ((amc - 1.0) * v * v - 2.0 * amc * cb * v + 1.0 + amc) / den
    s1sq = b2s / (1.0 + v * v - 2.0 * v * cb)
    s1 = torch.sqrt(s1sq.clamp(min=0.0))
    d = _polish_distances(s1, u * s1, v * s1, a2, b2, c2, ca, cb, cg)
    X = [tuple(s * jc for jc in ji) for s, ji in zip(d, j)]  # 3 points of (4, H)
    res = torch.stack([_dot(d, d) for d in (_sub(X[1], X[2]), _sub(X[0], X[2]), _sub(X[0], X[1]))])
    res = (res - torch.stack([a2, b2, c2])[:, None]).abs().amax(0)
    ref = torch.maximum(torch.maximum(a2, b2), c2)
    valid = real & (s1sq > 0) & (u > 0) & (v > 0) & (res <= residual_tol * ref)
    Fm, Fc = _triad(*P), _triad(*X)  # frames as (e1, e2, e3), each a Vec
    R = [[Fc[0][r] * Fm[0][c] + Fc[1][r] * Fm[1][c] + Fc[2][r] * Fm[2][c] for c in range(3)] for r in range(3)]
    Pm = tuple((P[0][k] + P[1][k] + P[2][k]) / 3.0 for k in range(3))
    Xm = tuple((X[0][k] + X[1][k] + X[2][k]) / 3.0 for k in range(3))
    t = [Xm[r] - (R[r][0] * Pm[0] + R[r][1] * Pm[1] + R[r][2] * Pm[2]) for r in range(3)]
    total = t[0] + t[1] + t[2]
    for row in R:
        total = total + row[0] + row[1] + row[2]
    return R, t, valid & torch.isfinite(total)  # a NaN or inf anywhere makes the sum non-finite


def _polish_distances(s1, s2, s3, a2, b2, c2, ca, cb, cg, steps: int = 2):
    """Newton steps on the three law-of-cosines equations in the distances (u from Grunert's formula
    loses digits where cos(gamma) - v cos(alpha) is small)."""
    for _ in range(steps):
        f1 = s2 * s2 + s3 * s3 - 2.0 * s2 * s3 * ca - a2
        f2 = s1 * s1 + s3 * s3 - 2.0 * s1 * s3 * cb - b2
        f3 = s1 * s1 + s2 * s2 - 2.0 * s1 * s2 * cg - c2
        # Jacobian rows (0, j12, j13), (j21, 0, j23), (j31, j32, 0); Cramer's rule.
        j12, j13 = 2.0 * (s2 - s3 * ca), 2.0 * (s3 - s2 * ca)
        j21, j23 = 2.0 * (s1 - s3 * cb), 2.0 * (s3 - s1 * cb)
        j31, j32 = 2.0 * (s1 - s2 * cg), 2.0 * (s2 - s1 * cg)
        det = j12 * j23 * j31 + j13 * j21 * j32
        ok = det.abs() > 1e-12 * (s1 * s1 + s2 * s2 + s3 * s3) ** 1.5
        det = torch.where(ok, det, torch.ones_like(det))
        m = j21 * f3 - f2 * j31
        d1 = (j12 * j23 * f3 + j13 * f2 * j32 - f1 * j23 * j32) / det
        d2 = (f1 * j23 * j31 + j13 * m) / det
        d3 = (f1 * j21 * j32 - j12 * m) / det
        s1, s2, s3 = (torch.where(ok, s - dd, s) for s, dd in ((s1, d1), (s2, d2), (s3, d3)))
    return s1, s2, s3


def _pack(R, t, valid) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """SoA (4, H) pieces -> R (H, 4, 3, 3), t (H, 4, 3), valid (H, 4), placeholders where invalid."""
    Rm = torch.stack([torch.stack(row, -1) for row in R], -2).transpose(0, 1)
    tm = torch.stack(t, -1).transpose(0, 1)
    valid = valid.T
    eye = torch.eye(3, dtype=Rm.dtype, device=Rm.device).expand_as(Rm)
    return torch.where(valid[..., None, None], Rm, eye), torch.where(valid[..., None], tm, torch.zeros_like(tm)), valid


def p3p(bearings: torch.Tensor, points: torch.Tensor, real_tol: float = 1e-3,
        residual_tol: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """All P3P solutions of H problems at once.

    ``bearings`` (H, 3, 3): bearing vectors of the three image points (any positive length; row i is
    point i), ``points`` (H, 3, 3): the model points. Returns ``R`` (H, 4, 3, 3), ``t`` (H, 4, 3) and
    ``valid`` (H, 4): a real root (see :func:`solve_quartic` for ``real_tol``) with positive distances
    whose camera-frame triangle reproduces the model's squared side lengths within ``residual_tol``
    (relative). Invalid slots hold finite placeholders (identity, zero).
    """
    j = [_unit(b) for b in _soa(bearings)]
    return _pack(*_p3p_soa(j, _soa(points), real_tol, residual_tol))


def p4p(uv: torch.Tensor, points: torch.Tensor, K: torch.Tensor, real_tol: float = 1e-3
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose hypotheses from 4 correspondences each: P3P on the first three, the 4th picks the solution.

    ``uv`` (H, 4, 2) pixel coordinates, ``points`` (H, 4, 3) model points, ``K`` (3, 3) (zero skew
    assumed for the bearings). Returns ``R`` (H, 3, 3), ``t`` (H, 3), ``err`` (H,) the 4th point's
    reprojection error in pixels (inf without a valid solution) and ``valid`` (H,). A solution must put
    the 4th point in front of the camera.
    """
    fx, fy, cx, cy, sk = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    c = uv.permute(1, 2, 0).contiguous()  # (4, 2, H)
    yb = [(c[i, 1] - cy) / fy for i in range(4)]
    bear = [((c[i, 0] - cx - sk * yb[i]) / fx, yb[i], torch.ones_like(yb[i])) for i in range(4)]
    P = _soa(points)
    R, t, valid = _p3p_soa([_unit(b) for b in bear[:3]], P[:3], real_tol, 1e-3)
    X4 = [R[r][0] * P[3][0] + R[r][1] * P[3][1] + R[r][2] * P[3][2] + t[r] for r in range(3)]  # (4, H) each
    z = X4[2]
    front = z > 1e-9
    zs = torch.where(front, z, torch.ones_like(z))
    u4 = (fx * X4[0] + sk * X4[1]) / zs + cx
    v4 = fy * X4[1] / zs + cy
    err = torch.sqrt((u4 - c[3, 0]) ** 2 + (v4 - c[3, 1]) ** 2)
    err = torch.where(valid & front & torch.isfinite(err), err, torch.full_like(err, math.inf))
    e, best = err.min(0)
    pick = lambda x: x.gather(0, best[None])[0]  # noqa: E731
    Rb = torch.stack([torch.stack([pick(x) for x in row], -1) for row in R], -2)
    tb = torch.stack([pick(x) for x in t], -1)
    ok = torch.isfinite(e)
    eye = torch.eye(3, dtype=Rb.dtype, device=Rb.device)
    return torch.where(ok[:, None, None], Rb, eye), torch.where(ok[:, None], tb, torch.zeros_like(tb)), e, ok
