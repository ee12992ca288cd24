"""Losses of SurfEmb / SurfSurg6D against brute-force loop references (float64, tiny sizes)."""

import math

import pytest
import torch

from surftrack.model.losses import (
    ALPHA_MAX,
    consistency_loss,
    info_nce,
    info_nce_batched,
    mask_bce,
    pen_log_weights,
    pen_nce,
    surfsurg6d_loss,
)

N, M, E, B = 5, 7, 4, 3
DT = torch.float64


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def randn(*shape, g):
    return torch.randn(*shape, generator=g, dtype=DT)


def unit_ball(*shape, g):
    """Points uniformly-ish inside the unit ball (normalised object coordinates)."""
    x = randn(*shape, 3, g=g)
    r = torch.rand(*shape, 1, generator=g, dtype=DT) ** (1 / 3)
    return x / x.norm(dim=-1, keepdim=True) * r


# ------------------------------------------------------------------------------------- loop references
def ref_info_nce(q, kp, kn, w=None):
    """-mean_i log(exp(lp) / (exp(lp) + sum_j w_ij exp(ln_j))) with explicit loops."""
    total = 0.0
    for i in range(q.shape[0]):
        lp = sum(float(q[i, e] * kp[i, e]) for e in range(q.shape[1]))
        den = math.exp(lp)
        for j in range(kn.shape[0]):
            ln = sum(float(q[i, e] * kn[j, e]) for e in range(q.shape[1]))
            den += (1.0 if w is None else float(w[i, j])) * math.exp(ln)
        total += -math.log(math.exp(lp) / den)
    return total / q.shape[0]


def dist(a, b):
    return math.sqrt(sum((float(a[k]) - float(b[k])) ** 2 for k in range(a.shape[0])))


def ref_pen_weights(cq, cn, alpha):
    """p_ij = 1 - alpha * log(||c_j - c_i|| + 1) with explicit loops, as an (N, M) tensor."""
    rows = [[1.0 - alpha * math.log(dist(cq[i], cn[j]) + 1.0) for j in range(cn.shape[0])]
            for i in range(cq.shape[0])]
    return torch.tensor(rows, dtype=DT)


def ref_consistency(c, emb, lam, m, normalize):
    P = c.shape[0]
    if normalize:
        emb = emb / emb.norm(dim=-1, keepdim=True)
    s, n = 0.0, 0
    for i in range(P):
        for j in range(i + 1, P):
            dc, de = dist(c[i], c[j]), dist(emb[i], emb[j])
            w = max(m, math.exp(-lam * dc))
            s += w * (dc - de) ** 2
            n += 1
    assert n == P * (P - 1) // 2
    return s * 2.0 / (P * (P - 1))


# ---------------------------------------------------------------------------------------------- InfoNCE
def test_info_nce_matches_loops():
    g = gen(1)
    q, kp, kn = randn(N, E, g=g), randn(N, E, g=g), randn(M, E, g=g)
    assert info_nce(q, kp, kn).item() == pytest.approx(ref_info_nce(q, kp, kn), rel=1e-12)


def test_info_nce_is_cross_entropy_target_zero():
    g = gen(2)
    q, kp, kn = randn(N, E, g=g), randn(N, E, g=g), randn(M, E, g=g)
    logits = torch.cat([(q * kp).sum(-1, keepdim=True), q @ kn.T], 1)
    ce = torch.nn.functional.cross_entropy(logits, torch.zeros(N, dtype=torch.long))
    torch.testing.assert_close(info_nce(q, kp, kn), ce, rtol=1e-13, atol=1e-13)


def test_info_nce_batched_equals_mean_of_images():
    g = gen(3)
    q, kp, kn = randn(B, N, E, g=g), randn(B, N, E, g=g), randn(B, M, E, g=g)
    lw = torch.log(torch.rand(B, N, M, generator=g, dtype=DT) + 0.1)
    for w in (None, lw):
        per_image = torch.stack([info_nce(q[b], kp[b], kn[b], None if w is None else w[b]) for b in range(B)])
        torch.testing.assert_close(info_nce_batched(q, kp, kn, w), per_image.mean(), rtol=1e-13, atol=1e-13)


def test_neg_log_weight_multiplies_exp_in_denominator():
    g = gen(4)
    q, kp, kn = randn(N, E, g=g), randn(N, E, g=g), randn(M, E, g=g)
    w = torch.rand(N, M, generator=g, dtype=DT) * 1.5 + 0.05
    got = info_nce(q, kp, kn, torch.log(w)).item()
    assert got == pytest.approx(ref_info_nce(q, kp, kn, w), rel=1e-12)
    assert got != pytest.approx(ref_info_nce(q, kp, kn), rel=1e-6)


def test_info_nce_input_checks():
    g = gen(5)
    q, kp, kn = randn(N, E, g=g), randn(N, E, g=g), randn(M, E, g=g)
    with pytest.raises(ValueError, match="k_pos"):
        info_nce(q, kp[:-1], kn)
    with pytest.raises(ValueError, match="k_neg"):
        info_nce(q, kp, kn[:, :-1])
    with pytest.raises(ValueError, match="neg_log_weight"):
        info_nce(q, kp, kn, torch.zeros(N, M + 1, dtype=DT))
    with pytest.raises(ValueError, match=r"\(N, E\)"):
        info_nce(q[None], kp, kn)
    with pytest.raises(TypeError, match="floating"):
        info_nce(q.long(), kp, kn)


# ----------------------------------------------------------------------------------------------- penNCE
@pytest.mark.parametrize("alpha", [0.1, 0.5, 0.9])
def test_pen_log_weights_match_loops(alpha):
    g = gen(6)
    cq, cn = unit_ball(N, g=g), unit_ball(M, g=g)
    got = pen_log_weights(cq, cn, alpha)
    assert got.shape == (N, M)
    ref = torch.log(ref_pen_weights(cq, cn, alpha))
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    # batched with broadcasting leading dims
    cqb, cnb = unit_ball(B, N, g=g), unit_ball(B, M, g=g)
    gotb = pen_log_weights(cqb, cnb, alpha)
    for b in range(B):
        refb = torch.log(ref_pen_weights(cqb[b], cnb[b], alpha))
        torch.testing.assert_close(gotb[b], refb, rtol=1e-12, atol=1e-12)


def test_pen_log_weights_extreme_pair_positive():
    """Antipodal points of the unit ball (d = 2) stay finite just below the bound."""
    cq = torch.tensor([[1.0, 0, 0]], dtype=DT)
    cn = torch.tensor([[-1.0, 0, 0]], dtype=DT)
    lw = pen_log_weights(cq, cn, ALPHA_MAX * (1 - 1e-9))
    assert torch.isfinite(lw).all()
    assert ALPHA_MAX == pytest.approx(1 / math.log(3))


def test_pen_log_weights_alpha_zero_exact_zeros():
    g = gen(7)
    lw = pen_log_weights(unit_ball(B, N, g=g), unit_ball(B, M, g=g), 0.0)
    assert lw.shape == (B, N, M) and lw.dtype == DT
    assert torch.equal(lw, torch.zeros(B, N, M, dtype=DT))


@pytest.mark.parametrize("alpha", [-1e-6, -1.0, ALPHA_MAX, 0.95, 1.0, float("nan"), float("inf")])
def test_pen_log_weights_invalid_alpha_raises(alpha):
    g = gen(8)
    with pytest.raises(ValueError, match="1/ln"):
        pen_log_weights(unit_ball(N, g=g), unit_ball(M, g=g), alpha)


def test_pen_log_weights_rejects_unnormalised_coords():
    cq = torch.tensor([[30.0, 0, 0]], dtype=DT)  # mm, not normalised: d = 60
    cn = torch.tensor([[-30.0, 0, 0]], dtype=DT)
    with pytest.raises(ValueError, match="NORMALISED"):
        pen_log_weights(cq, cn, 0.5)


def test_pen_nce_matches_loops_and_alpha_zero_is_info_nce():
    g = gen(9)
    q, kp, kn = randn(B, N, E, g=g), randn(B, N, E, g=g), randn(B, M, E, g=g)
    cq, cn = unit_ball(B, N, g=g), unit_ball(B, M, g=g)
    alpha = 0.6
    ref = sum(ref_info_nce(q[b], kp[b], kn[b], ref_pen_weights(cq[b], cn[b], alpha)) for b in range(B)) / B
    assert pen_nce(q, kp, kn, cq, cn, alpha).item() == pytest.approx(ref, rel=1e-12)
    assert torch.equal(pen_nce(q, kp, kn, cq, cn, 0.0), info_nce_batched(q, kp, kn))


def test_hard_negative_gets_more_gradient_than_easy():
    """Equal logits: the near (hard) negative must receive the larger share of the gradient."""
    q = torch.tensor([[[1.0, 0.0]]], dtype=DT)
    kp = torch.tensor([[[2.0, 0.0]]], dtype=DT)
    kn = torch.tensor([[[0.5, 0.3], [0.5, -0.3]]], dtype=DT, requires_grad=True)  # equal logits 0.5
    cq = torch.tensor([[[0.0, 0.0, 0.0]]], dtype=DT)
    cn = torch.tensor([[[0.05, 0.0, 0.0], [0.0, 0.0, 0.95]]], dtype=DT)  # near, far
    grads = {}
    for alpha in (0.0, 0.8):
        (gk,) = torch.autograd.grad(pen_nce(q, kp, kn, cq, cn, alpha), kn)
        grads[alpha] = gk[0].norm(dim=-1)
    # InfoNCE: equal logits -> equal gradients
    torch.testing.assert_close(grads[0.0][0], grads[0.0][1])
    # penNCE: the hard (near) negative dominates
    near, far = grads[0.8]
    assert near > far * 1.5
    # and the weights themselves: near ~1, far < near
    lw = pen_log_weights(cq, cn, 0.8)[0, 0]
    assert lw[0] > lw[1] and lw[0] <= 0


# ------------------------------------------------------------------------------------------ consistency
@pytest.mark.parametrize("normalize", [True, False])
@pytest.mark.parametrize("lam,m", [(10.0, 0.01), (3.0, 0.2)])
def test_consistency_matches_double_loop(normalize, lam, m):
    g = gen(10)
    P = 7
    c, emb = unit_ball(P, g=g), randn(P, E, g=g) * 0.5
    got = consistency_loss(c, emb, lam=lam, m=m, normalize=normalize)
    assert got.item() == pytest.approx(ref_consistency(c, emb, lam, m, normalize), rel=1e-12)
    # batched: mean over the leading dim
    cb, eb = unit_ball(B, P, g=g), randn(B, P, E, g=g)
    gotb = consistency_loss(cb, eb, lam=lam, m=m, normalize=normalize)
    refb = sum(ref_consistency(cb[b], eb[b], lam, m, normalize) for b in range(B)) / B
    assert gotb.item() == pytest.approx(refb, rel=1e-12)


def test_consistency_weight_floor_applies():
    # two points 0.8 apart: exp(-10 * 0.8) = 3.4e-4 < m = 0.01 -> the floor is the weight
    c = torch.tensor([[0.0, 0, 0], [0.8, 0, 0]], dtype=DT)
    emb = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=DT)  # embedding distance 0
    assert consistency_loss(c, emb, lam=10.0, m=0.01).item() == pytest.approx(0.01 * 0.8**2, rel=1e-12)
    assert consistency_loss(c, emb, lam=10.0, m=0.0).item() == pytest.approx(math.exp(-8) * 0.64, rel=1e-12)
    # near pair: exp wins over the floor
    c2 = torch.tensor([[0.0, 0, 0], [0.1, 0, 0]], dtype=DT)
    assert consistency_loss(c2, emb, lam=10.0, m=0.01).item() == pytest.approx(math.exp(-1) * 0.01, rel=1e-12)


def test_consistency_finite_gradients_with_duplicates():
    g = gen(11)
    c = unit_ball(6, g=g)
    emb = randn(6, E, g=g)
    c[3] = c[1]          # duplicate point i != j: identical coordinates ...
    emb[3] = emb[1]      # ... and identical embeddings (both distances exactly 0)
    c.requires_grad_(True)
    emb.requires_grad_(True)
    for normalize in (True, False):
        loss = consistency_loss(c, emb, normalize=normalize)
        gc, ge = torch.autograd.grad(loss, (c, emb))
        assert torch.isfinite(loss) and torch.isfinite(gc).all() and torch.isfinite(ge).all()
    # all points identical (every pair at distance 0) and a single pair i = j is excluded by design
    c0 = torch.zeros(4, 3, dtype=DT, requires_grad=True)
    e0 = torch.ones(4, E, dtype=DT, requires_grad=True)
    loss = consistency_loss(c0, e0)
    gc, ge = torch.autograd.grad(loss, (c0, e0))
    assert loss.item() == 0.0 and torch.isfinite(gc).all() and torch.isfinite(ge).all()


def test_consistency_float32_finite_gradients_duplicates():
    c = torch.tensor([[0.1, 0.2, 0.3]] * 3 + [[0.0, 0.0, 0.0]], requires_grad=True)
    e = torch.tensor([[1.0, 2.0, 3.0, 4.0]] * 3 + [[0.0, 0.0, 0.0, 0.0]], requires_grad=True)  # zero emb too
    gc, ge = torch.autograd.grad(consistency_loss(c, e), (c, e))
    assert torch.isfinite(gc).all() and torch.isfinite(ge).all()


def test_consistency_input_checks():
    with pytest.raises(ValueError, match="P >= 2"):
        consistency_loss(torch.zeros(1, 3, dtype=DT), torch.zeros(1, E, dtype=DT))
    with pytest.raises(ValueError, match="emb"):
        consistency_loss(torch.zeros(5, 3, dtype=DT), torch.zeros(4, E, dtype=DT))
    with pytest.raises(ValueError, match="coords"):
        consistency_loss(torch.zeros(5, 2, dtype=DT), torch.zeros(5, E, dtype=DT))
    with pytest.raises(ValueError, match="m must"):
        consistency_loss(torch.zeros(5, 3, dtype=DT), torch.zeros(5, E, dtype=DT), m=-0.1)


# ---------------------------------------------------------------------------------------------- gradcheck
def test_gradcheck_info_nce():
    g = gen(12)
    args = (randn(2, 3, E, g=g), randn(2, 3, E, g=g), randn(2, 4, E, g=g), randn(2, 3, 4, g=g) * 0.3)
    args = tuple(a.requires_grad_(True) for a in args)
    assert torch.autograd.gradcheck(info_nce_batched, args)
    assert torch.autograd.gradcheck(info_nce, tuple(a[0].detach().requires_grad_(True) for a in args))


def test_gradcheck_pen_nce():
    g = gen(13)
    q, kp, kn = (randn(2, 3, E, g=g).requires_grad_(True), randn(2, 3, E, g=g).requires_grad_(True),
                 randn(2, 4, E, g=g).requires_grad_(True))
    cq, cn = unit_ball(2, 3, g=g).requires_grad_(True), unit_ball(2, 4, g=g).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda *a: pen_nce(*a, alpha=0.7), (q, kp, kn, cq, cn))


def test_gradcheck_consistency():
    g = gen(14)
    c, emb = unit_ball(2, 5, g=g).requires_grad_(True), randn(2, 5, E, g=g).requires_grad_(True)
    for normalize in (True, False):
        assert torch.autograd.gradcheck(lambda a, b: consistency_loss(a, b, lam=4.0, normalize=normalize), (c, emb))


# ----------------------------------------------------------------------------------------- mask + total
def test_mask_bce_matches_loops():
    g = gen(15)
    x = randn(2, 3, 4, g=g) * 3
    y = torch.rand(2, 3, 4, generator=g) > 0.5
    ref = 0.0
    for v, t in zip(x.flatten().tolist(), y.flatten().tolist()):
        p = 1 / (1 + math.exp(-v))
        ref += -(math.log(p) if t else math.log(1 - p))
    assert mask_bce(x, y).item() == pytest.approx(ref / x.numel(), rel=1e-12)
    with pytest.raises(ValueError, match="shape"):
        mask_bce(x, y[0])


def _total_inputs(seed):
    g = gen(seed)
    return dict(
        mask_logits=randn(B, 6, 6, g=g), mask_target=(torch.rand(B, 6, 6, generator=g) > 0.4).to(DT),
        q=randn(B, N, E, g=g), k_pos=randn(B, N, E, g=g), k_neg=randn(B, M, E, g=g),
        c_query=unit_ball(B, N, g=g), c_neg=unit_ball(B, M, g=g),
    )


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_alpha_beta_zero_is_surfemb_baseline_exactly(seed, dtype):
    inp = {k: v.to(dtype) for k, v in _total_inputs(seed).items()}
    out = surfsurg6d_loss(**inp, alpha=0.0, beta=0.0)
    base = mask_bce(inp["mask_logits"], inp["mask_target"]) + info_nce_batched(inp["q"], inp["k_pos"], inp["k_neg"])
    assert torch.equal(out["total"], base)
    assert out["con"].item() == 0.0
    # positional call in the documented order
    out2 = surfsurg6d_loss(*inp.values(), None, None, 0.0, 0.0)
    assert torch.equal(out2["total"], base)


def test_total_components():
    inp = _total_inputs(20)
    kc = torch.cat([inp["c_neg"], inp["c_query"]], 1)
    ke = torch.cat([inp["k_neg"], inp["k_pos"]], 1)
    out = surfsurg6d_loss(**inp, key_coords=kc, key_emb=ke, alpha=0.5, beta=2.0)
    torch.testing.assert_close(out["mask"], mask_bce(inp["mask_logits"], inp["mask_target"]))
    torch.testing.assert_close(out["nce"], pen_nce(inp["q"], inp["k_pos"], inp["k_neg"],
                                                   inp["c_query"], inp["c_neg"], 0.5))
    torch.testing.assert_close(out["con"], consistency_loss(kc, ke))
    torch.testing.assert_close(out["total"], out["mask"] + out["nce"] + 2.0 * out["con"])
    # default consistency set = the negatives
    out_d = surfsurg6d_loss(**inp, alpha=0.5, beta=1.0)
    torch.testing.assert_close(out_d["con"], consistency_loss(inp["c_neg"], inp["k_neg"]))
    with pytest.raises(ValueError, match="both"):
        surfsurg6d_loss(**inp, key_coords=kc, alpha=0.5, beta=1.0)
    with pytest.raises(ValueError, match="beta"):
        surfsurg6d_loss(**inp, alpha=0.5, beta=-1.0)
    with pytest.raises(ValueError, match="1/ln"):
        surfsurg6d_loss(**inp, alpha=1.0, beta=1.0)


def test_floor_admits_the_papers_alpha_and_clamps_weights():
    """The paper trains with alpha = 1; with a floor on p_ij every pair in the unit ball stays defined."""
    import math

    from surftrack.model.losses import pen_log_weights

    c_q = torch.tensor([[[1.0, 0.0, 0.0]]], dtype=torch.float64)
    c_n = torch.tensor([[[-1.0, 0.0, 0.0], [0.9, 0.0, 0.0]]], dtype=torch.float64)
    with pytest.raises(ValueError):
        pen_log_weights(c_q, c_n, 1.0)
    lw = pen_log_weights(c_q, c_n, 1.0, floor=0.01)
    assert torch.allclose(lw[0, 0, 0], torch.tensor(math.log(0.01), dtype=torch.float64))
    assert torch.allclose(lw[0, 0, 1], torch.tensor(math.log(1 - math.log(1.1)), dtype=torch.float64))
    with pytest.raises(ValueError):
        pen_log_weights(c_q, c_n, 1.0, floor=1.5)
