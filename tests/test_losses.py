"""Chamfer (Eq. 1), pose loss (Eq. 2) and the joint loss against independent references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.train.losses import JointLoss, chamfer_distance, pose_loss


def brute_chamfer(x: np.ndarray, y: np.ndarray) -> float:
    """Double loop, float64: mean nearest Euclidean distance both ways."""
    a = np.mean([min(np.linalg.norm(p - q) for q in y) for p in x])
    b = np.mean([min(np.linalg.norm(p - q) for p in x) for q in y])
    return float(a + b)


def naive_chamfer_torch(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Differentiable reference: full distance matrix with gradient, then min."""
    d = torch.sqrt(((x[:, None, :] - y[None, :, :]) ** 2).sum(-1))
    return d.min(1).values.mean() + d.min(0).values.mean()


def test_chamfer_matches_brute_force_with_padding():
    rng = np.random.default_rng(0)
    sizes = [(7, 5), (3, 9), (9, 9)]
    xs = [rng.normal(size=(p, 3)) + 20.0 for p, _ in sizes]  # far from the origin on purpose
    ys = [rng.normal(size=(q, 3)) + 20.0 for _, q in sizes]
    x = torch.zeros(3, 9, 3)
    y = torch.full((3, 9, 3), 1e3)  # padding far away: must be ignored
    for i, (p, q) in enumerate(sizes):
        x[i, :p] = torch.from_numpy(xs[i]).float()
        y[i, :q] = torch.from_numpy(ys[i]).float()
    cd = chamfer_distance(x, y, torch.tensor([p for p, _ in sizes]),
                          torch.tensor([q for _, q in sizes]))
    ref = [brute_chamfer(a, b) for a, b in zip(xs, ys, strict=True)]
    np.testing.assert_allclose(cd.numpy(), ref, rtol=1e-5, atol=1e-5)


def test_chamfer_gradient_equals_naive():
    rng = np.random.default_rng(1)
    x0 = torch.from_numpy(rng.normal(size=(12, 3))).double()
    y0 = torch.from_numpy(rng.normal(size=(8, 3))).double()
    x1, y1 = x0.clone().requires_grad_(), y0.clone().requires_grad_()
    chamfer_distance(x1[None], y1[None]).sum().backward()
    x2, y2 = x0.clone().requires_grad_(), y0.clone().requires_grad_()
    naive_chamfer_torch(x2, y2).backward()
    torch.testing.assert_close(x1.grad, x2.grad, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(y1.grad, y2.grad, rtol=1e-10, atol=1e-12)


def test_chamfer_padded_rows_get_no_gradient_and_identity_is_zero():
    x = torch.randn(1, 6, 3, requires_grad=True)
    y = x.detach().clone()
    cd = chamfer_distance(x, y, torch.tensor([4]), torch.tensor([4]))
    assert float(cd.detach()) == pytest.approx(0.0, abs=1e-7)
    cd = chamfer_distance(x, y + 0.1, torch.tensor([4]), torch.tensor([6]))
    cd.backward()
    assert torch.all(x.grad[0, 4:] == 0) and torch.any(x.grad[0, :4] != 0)
    assert torch.isfinite(x.grad).all()


def test_chamfer_empty_cloud_is_zero():
    x, y = torch.randn(2, 4, 3), torch.randn(2, 5, 3)
    cd = chamfer_distance(x, y, torch.tensor([0, 4]), torch.tensor([5, 0]))
    assert torch.equal(cd, torch.zeros(2))


def _complete(rng, m=200):
    return rng.uniform(-1, 1, size=(m, 3)) * np.array([2.2, 0.9, 0.7])


def test_pose_loss_zero_at_truth_positive_otherwise_order_free():
    rng = np.random.default_rng(2)
    c = _complete(rng)
    gt = np.array([12.0, -3.0, -1.0, 0.7])
    x = torch.from_numpy(canonical_to_sensor(c, gt))[None]
    g = torch.from_numpy(gt)[None]
    assert float(pose_loss(g, g, x)) == pytest.approx(0.0, abs=1e-20)
    wrong = g + torch.tensor([[0.0, 0.0, 0.0, 0.1]], dtype=torch.float64)
    v = float(pose_loss(wrong, g, x))
    assert v > 0
    perm = torch.from_numpy(rng.permutation(x.shape[1]))
    assert float(pose_loss(wrong, g, x[:, perm])) == pytest.approx(v, rel=1e-12)


def test_pose_loss_pure_translation_is_d_squared():
    rng = np.random.default_rng(3)
    gt = torch.tensor([[5.0, 2.0, -1.0, 1.1]], dtype=torch.float64)
    x = torch.from_numpy(canonical_to_sensor(_complete(rng), gt[0].numpy()))[None]
    d = torch.tensor([[0.3, -0.4, 0.0, 0.0]], dtype=torch.float64)
    assert float(pose_loss(gt + d, gt, x)) == pytest.approx(0.25, rel=1e-12)


def test_pose_loss_matches_numpy_reference_with_lengths():
    rng = np.random.default_rng(4)
    gt, pred = np.array([8.0, 1.0, -0.8, -2.0]), np.array([8.3, 0.7, -0.7, -1.6])
    x = canonical_to_sensor(_complete(rng, 50), gt)
    ref = np.mean(np.sum((sensor_to_canonical(x, pred) - sensor_to_canonical(x, gt)) ** 2, 1))
    padded = np.concatenate([x, np.full((10, 3), 99.0)])[None]
    got = pose_loss(torch.from_numpy(pred[None]), torch.from_numpy(gt[None]),
                    torch.from_numpy(padded),
                    torch.tensor([50]))
    assert float(got) == pytest.approx(ref, rel=1e-10)


def test_joint_loss_formula_and_optimum():
    j = JointLoss()
    with torch.no_grad():
        j.log_sigma.copy_(torch.tensor([math.log(0.2), math.log(0.5)]))
    l_cd, l_p = torch.tensor(0.03), torch.tensor(0.4)
    ref = 0.03 / (2 * 0.04) + 0.4 / (2 * 0.25) + math.log(0.2 * 0.5)
    assert float(j(l_cd, l_p).detach()) == pytest.approx(ref, rel=1e-6)
    j.init_from(0.03, 0.4)  # s^2 = L is the stationary point
    j.zero_grad()
    j(l_cd, l_p).backward()
    assert torch.allclose(j.log_sigma.grad, torch.zeros(2), atol=1e-6)
