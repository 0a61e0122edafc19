"""Dense blocks of the joint-space inertia matrix, read from the backends' sparse ``mass_matrix`` on the device.

Both backends expose M(q) as MuJoCo stores it (``MjData.M``, mujoco-warp's ``Data.M``): the lower triangle of the
symmetric nv × nv matrix, row ``i`` holding ``mj_model.M_rownnz[i]`` values from ``M_rowadr[i]`` on, in the columns
``M_colind`` (ascending, the diagonal last). Its pattern is the dof tree's: ``M[i, j]`` with ``j < i`` is stored when
dof ``j`` is an ancestor of dof ``i``, and every other entry is structurally zero (for TOCABI, nv = 39 and 396
stored values). mujoco-warp keeps this layout whatever ``opt.jacobian`` says: its dense/sparse choice (``nv > 32`` is
sparse under ``mjJAC_AUTO``) only changes how the factor ``qLD`` is stored.

:class:`DenseBlock` turns that into a dense ``(N, k, k)`` block for a list of dofs with one ``index_select`` and one
multiply by a 0/1 mask into preallocated buffers: no host synchronisation, the same kernels every call, so it can
sit inside a captured CUDA graph.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

__all__ = ["csr_block_index", "DenseBlock"]


def csr_block_index(mj: mujoco.MjModel, dofs) -> tuple[np.ndarray, np.ndarray]:
    """Where each entry of the dense block ``M[dofs][:, dofs]`` lives in the sparse vector ``MjData.M``.

    Returns ``(index, stored)``, both (k, k): ``index[a, b]`` the address of ``M[max(i, j), min(i, j)]`` for
    ``i, j = dofs[a], dofs[b]`` (0 where the entry is structurally zero) and ``stored[a, b]`` whether it is stored.
    """
    dofs = [int(d) for d in dofs]
    if any(not 0 <= d < mj.nv for d in dofs):
        raise ValueError(f"dofs {dofs} out of range for a model with nv = {mj.nv}")
    k = len(dofs)
    index, stored = np.zeros((k, k), dtype=np.int64), np.zeros((k, k), dtype=bool)
    for a, i in enumerate(dofs):
        for b, j in enumerate(dofs):
            row, col = max(i, j), min(i, j)
            start = int(mj.M_rowadr[row])
            cols = np.asarray(mj.M_colind[start : start + int(mj.M_rownnz[row])])
            hit = np.flatnonzero(cols == col)
            if len(hit):
                index[a, b], stored[a, b] = start + int(hit[0]), True
    if not stored.diagonal().all():
        raise ValueError("the inertia matrix's sparse pattern lacks a diagonal entry; is mj_model.M_colind filled?")
    return index, stored


class DenseBlock:
    """The dense block ``M[dofs][:, dofs]`` of the backends' ``mass_matrix`` (N, nC), batched on the device.

    Args:
        mj: the compiled model (its ``M_rowadr``/``M_rownnz``/``M_colind`` give the layout).
        dofs: the k dof indices of the block (e.g. the leg joints' ``jnt_dofadr``).
        num_worlds: N.
        device: where the simulator's tensors live.

    Calling it with the (N, nC) sparse tensor returns a preallocated (N, k, k) float32 tensor, overwritten by the next
    call (clone what you keep).
    """

    def __init__(self, mj: mujoco.MjModel, dofs, num_worlds: int, device: torch.device | str):
        index, stored = csr_block_index(mj, dofs)
        self.k = k = index.shape[0]
        self.index = torch.as_tensor(index.reshape(-1), device=device)
        self.stored = torch.as_tensor(stored.reshape(-1), dtype=torch.float32, device=device)
        self._flat = torch.zeros(num_worlds, k * k, dtype=torch.float32, device=device)
        self.out = self._flat.view(num_worlds, k, k)

    def __call__(self, mass_matrix: torch.Tensor) -> torch.Tensor:
        torch.index_select(mass_matrix, 1, self.index, out=self._flat)
        self._flat.mul_(self.stored)
        return self.out
