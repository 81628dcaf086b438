"""Training losses: Chamfer distance (Eq. 1), pose loss (Eq. 2), joint loss with learned sigmas.

All inputs are in metres in the same (sensor) frame; nothing is normalised or rescaled, so
``chamfer_distance`` is in metres and ``pose_loss`` in square metres.

The Chamfer distance first finds each point's nearest neighbour without gradient, then
recomputes the distances to those neighbours with gradient. Two exact searches find them:
``"dense"`` (all pairwise distances, one batched matrix product per direction: any device) and
``"kdtree"`` (a k-d tree per cloud, :class:`scipy.spatial.cKDTree`, float64: CPU only, about
twice as fast on 1024-point vehicle clouds because the dense search is bound by the row-wise
argmin over P x Q distances, not by arithmetic). Both give the true nearest neighbour; they can
differ only where two neighbours are equally near to within float32 rounding (the distance is
then the same to ~1e-7 m).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn

from seqshape.model.transforms import unplace_points

_CHUNK_ELEMENTS = 1 << 22  # (b, P, Q) distances per chunk: 16 MB of float32 stays in cache
#: ``method="auto"`` uses the k-d trees on CPU when both clouds have at least this many rows
#: (below it the dense search's few small products are cheaper than building trees).
KDTREE_MIN_POINTS = 64
NN_METHODS = ("auto", "dense", "kdtree")


def _valid_mask(lengths: torch.Tensor | None, b: int, n: int, device) -> torch.Tensor:
    if lengths is None:
        return torch.ones(b, n, dtype=torch.bool, device=device)
    return torch.arange(n, device=device) < lengths.to(device).long().unsqueeze(-1)


@torch.no_grad()
def _argmin_sq(a: torch.Tensor, b: torch.Tensor, b_mask: torch.Tensor) -> torch.Tensor:
    """For each row of ``a`` (b, P, 3) the index of the nearest valid row of ``b`` (b, Q, 3).

    ``|b|^2 - 2 a.b`` (the ``|a|^2`` term does not change the argmin) as one batched product
    of 4-vectors ``[a, 1] . [-2 b, |b|^2]``; invalid rows of ``b`` get ``|b|^2 = +inf``.
    """
    sq = (b * b).sum(-1, keepdim=True).masked_fill(~b_mask.unsqueeze(-1), math.inf)
    a4 = torch.cat([a, torch.ones_like(a[..., :1])], -1)
    b4 = torch.cat([-2.0 * b, sq], -1)
    return torch.bmm(a4, b4.transpose(1, 2)).min(dim=2).indices


@torch.no_grad()
def _nearest_indices_dense(x: torch.Tensor, y: torch.Tensor, x_mask: torch.Tensor,
                           y_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Index of the nearest valid y for each x (B, P) and nearest valid x for each y (B, Q).

    Both clouds are first shifted by the same per-pair offset (the first y point) so that the
    expanded squared distances keep float32 precision far from the sensor origin.
    """
    b, p, q = x.shape[0], x.shape[1], y.shape[1]
    if q > 0:
        centre = y[:, :1]
        x, y = x - centre, y - centre
    chunk = max(1, _CHUNK_ELEMENTS // max(1, p * q))
    ix, iy = [], []
    for s in range(0, b, chunk):
        xs, ys = x[s:s + chunk], y[s:s + chunk]
        ix.append(_argmin_sq(xs, ys, y_mask[s:s + chunk]))
        iy.append(_argmin_sq(ys, xs, x_mask[s:s + chunk]))
    return torch.cat(ix), torch.cat(iy)


@torch.no_grad()
def _nearest_indices_kdtree(x: torch.Tensor, y: torch.Tensor, x_len: np.ndarray,
                            y_len: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_nearest_indices_dense` with one k-d tree per cloud (CPU, finite points).

    ``x_len`` / ``y_len`` (B,) real rows per cloud (the valid rows come first). Distances are
    evaluated in float64 on the points' float32 values; padded rows get index 0 (their
    distances are masked out by the caller), and so do all rows of a pair with an empty cloud.
    """
    xs = x.double().numpy()  # (B, P, 3)
    ys = y.double().numpy()  # (B, Q, 3)
    ix = np.zeros(x.shape[:2], np.int64)
    iy = np.zeros(y.shape[:2], np.int64)
    for k, (p, q) in enumerate(zip(x_len.tolist(), y_len.tolist(), strict=True)):
        if p == 0 or q == 0:
            continue
        ix[k, :p] = cKDTree(ys[k, :q]).query(xs[k, :p])[1]
        iy[k, :q] = cKDTree(xs[k, :p]).query(ys[k, :q])[1]
    return torch.from_numpy(ix), torch.from_numpy(iy)


def _use_kdtree(method: str, x: torch.Tensor, y: torch.Tensor) -> bool:
    if method not in NN_METHODS:
        raise ValueError(f"unknown nearest-neighbour method {method!r}; choose from {NN_METHODS}")
    if method == "dense" or x.device.type != "cpu":
        return False
    if method == "auto" and min(x.shape[1], y.shape[1]) < KDTREE_MIN_POINTS:
        return False
    return bool(torch.isfinite(x).all() and torch.isfinite(y).all())


def _nearest_indices(x: torch.Tensor, y: torch.Tensor, x_mask: torch.Tensor,
                     y_mask: torch.Tensor, method: str = "auto"
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest-neighbour indices both ways (see :func:`_nearest_indices_dense`) by ``method``.

    The masks are lengths masks (real rows first, :func:`_valid_mask`). ``"kdtree"`` falls
    back to ``"dense"`` off the CPU and on non-finite points (the loss is then NaN as before).
    """
    if _use_kdtree(method, x, y):
        return _nearest_indices_kdtree(x, y, x_mask.sum(1).numpy(), y_mask.sum(1).numpy())
    return _nearest_indices_dense(x, y, x_mask, y_mask)


def _gather(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    return torch.gather(points, 1, idx.unsqueeze(-1).expand(-1, -1, 3))


def chamfer_distance(x: torch.Tensor, y: torch.Tensor, x_lengths: torch.Tensor | None = None,
                     y_lengths: torch.Tensor | None = None, method: str = "auto") -> torch.Tensor:
    """Symmetric Chamfer distance (paper Eq. 1), Euclidean (not squared), per cloud pair.

    ``mean_{x} min_{y} |x - y| + mean_{y} min_{x} |x - y|`` for ``x`` (B, P, 3), ``y``
    (B, Q, 3); optional ``x_lengths`` / ``y_lengths`` (B,) mark padded rows as absent. Returns
    (B,), metres. Exact: the nearest neighbours are found without gradient, then gathered and
    the distances recomputed with gradient (the gradient of a min is the gradient at its
    argmin, so this equals the naive version's gradient). Pairs where a cloud is empty give 0.

    ``method`` chooses the neighbour search (module docstring): ``"dense"`` (batched matrix
    products, any device), ``"kdtree"`` (CPU k-d trees) or ``"auto"`` (k-d trees on CPU for
    clouds of at least :data:`KDTREE_MIN_POINTS` points, else dense).
    """
    b, p, q = x.shape[0], x.shape[1], y.shape[1]
    x_mask = _valid_mask(x_lengths, b, p, x.device)
    y_mask = _valid_mask(y_lengths, b, q, x.device)
    ix, iy = _nearest_indices(x.detach(), y.detach(), x_mask, y_mask, method)
    ix, iy = ix.to(x.device), iy.to(x.device)
    dx = torch.linalg.vector_norm(x - _gather(y, ix), dim=-1)  # (B, P)
    dy = torch.linalg.vector_norm(y - _gather(x, iy), dim=-1)  # (B, Q)
    nx = x_mask.sum(1).clamp(min=1)
    ny = y_mask.sum(1).clamp(min=1)
    both = (x_mask.any(1) & y_mask.any(1)).to(x.dtype)
    cd = (dx * x_mask).sum(1) / nx + (dy * y_mask).sum(1) / ny
    return cd * both


def pose_inverse_apply(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``T^-1 x`` for planar poses (B, 4) = (x, y, z, yaw) and sensor points (B, M, 3).

    ``T`` maps canonical to sensor (``p = R_z(yaw) c + t``), so ``T^-1 p = R_z(yaw)^T (p - t)``.
    """
    return unplace_points(points, pose)


def pose_loss(pose_pred: torch.Tensor, pose_gt: torch.Tensor, gt_points: torch.Tensor,
              gt_lengths: torch.Tensor | None = None) -> torch.Tensor:
    """Pose loss (paper Eq. 2): ``mean_x |T^-1 x - T_gt^-1 x|^2`` over ground-truth points.

    ``pose_pred``, ``pose_gt`` (B, 4) planar poses in the sensor frame; ``gt_points`` (B, M, 3)
    the ground-truth complete shape in the sensor frame (optional ``gt_lengths`` (B,) for
    padding). Returns (B,) in m^2. A pure translation error d gives |d|^2.
    """
    diff = pose_inverse_apply(pose_pred, gt_points) - pose_inverse_apply(pose_gt, gt_points)
    sq = (diff * diff).sum(-1)
    mask = _valid_mask(gt_lengths, sq.shape[0], sq.shape[1], sq.device).to(sq.dtype)
    return (sq * mask).sum(1) / mask.sum(1).clamp(min=1)


class JointLoss(nn.Module):
    """Joint loss with learned uncertainties (paper's stage 3, Kendall et al.)::

        L = L_CD / (2 s_cd^2) + L_P / (2 s_p^2) + log(s_cd * s_p)

    parametrised by ``log_sigma = (log s_cd, log s_p)`` (a learnable (2,) parameter). Its
    optimum for fixed losses is ``s^2 = L``; :meth:`init_from` starts there.
    """

    def __init__(self):
        super().__init__()
        self.log_sigma = nn.Parameter(torch.zeros(2))

    @torch.no_grad()
    def init_from(self, l_cd: float, l_p: float) -> None:
        """Set ``s^2`` to the given loss values (clamped to >= 1e-8)."""
        self.log_sigma.copy_(0.5 * torch.log(torch.tensor([l_cd, l_p]).clamp(min=1e-8)))

    @property
    def sigmas(self) -> tuple[float, float]:
        s = self.log_sigma.detach().exp()
        return float(s[0]), float(s[1])

    def forward(self, l_cd: torch.Tensor, l_p: torch.Tensor) -> torch.Tensor:
        inv = torch.exp(-2.0 * self.log_sigma)
        return 0.5 * inv[0] * l_cd + 0.5 * inv[1] * l_p + self.log_sigma.sum()
