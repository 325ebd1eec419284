"""Inference arithmetic whose result for one agent never depends on which other samples share its batch.

Per-sample noise seeds made every random draw batch-independent, but the float32 arithmetic was not: on ETH's
eth/test with the shipped checkpoint, 199 of 253 samples predicted alone differed from the same samples predicted
in one batch (up to 1.6e-5 m at the stage level, batch 1 against 7 and 64). Four kinds of kernel moved bits, each
fixed here or at its one call site:

* GEMMs pick their kernel and summation order by shape (and a GEMV-shaped one, N = 1 or 2, by alignment):
  ``row_mm`` runs every product as one ``torch.mm`` per ``ROW_BLOCK``-row block, each 64-byte aligned (in place,
  or a zero-padded copy), so a row meets the same kernel, shape and alignment wherever it sits (``RowLinear``,
  LSTM_E/LSTM_D, the AIN GRU; ``tests/model/test_row_blocks.py``);
* transcendental functions round apart in torch's vectorised body and its scalar tail: ``sigmoid`` pads to whole
  blocks (the mode gate: a single agent's 20 gates sit in the tail);
* dividing by a Python number is a reciprocal multiply in the vectorised body and a true division in the tail:
  ``scale_down`` multiplies by the reciprocal everywhere;
* as a precaution of the same kind (not isolated by itself), the decoder turns its steps into each agent's basis
  and measures their lengths with products and sums rather than an einsum's bmm and a norm's reduction
  (``fast_decoder``, ``decoder.agent_output_basis``).

Checked: every eth/test sample alone against all in one batch, and ``logpipe predict`` at batch 1, 7 and 64 on ETH
and at 1, 5 and 64 on the driving model's AV1 hash/test (rasters and EN), all bit-identical on this machine
(tests: ``tests/stages/test_predict_batch_invariance.py``). Other CPUs take other kernels: bits may differ between
machines, never between batchings on one. Only inference uses this (``torch.is_grad_enabled()`` false): training
keeps torch's kernels and its bits. Cost (``make bench``, same run): the network without EN ~13 % slower, with EN
~3 %.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

ROW_BLOCK = 256
"""Rows per block: a multiple of the GEMM micro-kernels' row tiles; 64 cost the ETH network 30 % of its throughput in
Python calls, 256 about 13 %."""


_ALIGNMENT = 64
"""Bytes: the alignment of torch's CPU allocator (c10's ``gAlignment``), where a fresh copy's blocks start."""


def row_mm(x: Tensor, w: Tensor, bias: Tensor | None = None) -> Tensor:
    """``x @ w (+ bias)`` for ``x`` (M, K), ``w`` (K, N): row i of the result depends only on row i of ``x``."""
    rows, width = x.shape
    # Every block starts on the allocator's 64-byte alignment (a GEMV-shaped block, N = 1 or 2, is summed in
    # another order at another alignment) with the row stride ``width``: the whole blocks of a contiguous, aligned
    # ``x`` are such blocks already (ROW_BLOCK, a multiple of 64, rows span a multiple of 64 bytes); otherwise, and for
    # the last part-block, a fresh zero-padded copy is.
    whole = rows - rows % ROW_BLOCK if x.is_contiguous() and x.data_ptr() % _ALIGNMENT == 0 else 0
    tail = rows - whole
    padded = x.new_zeros(tail + (-tail) % ROW_BLOCK, width)
    padded[:tail] = x[whole:]
    # One mm per block: a single GEMM over all blocks (matmul folds them) or a batched one (bmm) picks its kernel
    # by the block count, which moved single-agent samples' bits.
    out = x.new_empty(whole + padded.shape[0], w.shape[1])
    for lo in range(0, out.shape[0], ROW_BLOCK):
        block = x[lo : lo + ROW_BLOCK] if lo < whole else padded[lo - whole : lo - whole + ROW_BLOCK]
        torch.mm(block, w, out=out[lo : lo + ROW_BLOCK])
    return out[:rows] if bias is None else out[:rows] + bias


class RowLinear(nn.Linear):
    """``nn.Linear`` (same parameters, same state-dict keys) that runs ``row_mm`` at inference."""

    def forward(self, x: Tensor) -> Tensor:
        if torch.is_grad_enabled() or x.numel() == 0:
            return super().forward(x)
        flat = row_mm(x.reshape(-1, x.shape[-1]), self.weight.t(), self.bias)
        return flat.view(*x.shape[:-1], self.out_features)


def gru_cell(cell: nn.GRUCell, x: Tensor, h: Tensor | None) -> Tensor:
    """``cell(x, h)`` (h None: zeros); at inference the same GRU equations (r, z, n gates) on ``row_mm``."""
    if torch.is_grad_enabled():
        return cell(x, h)  # type: ignore[no-any-return]
    if h is None:
        h = x.new_zeros(x.shape[0], cell.hidden_size)
    gi = row_mm(x, cell.weight_ih.t(), cell.bias_ih)
    gh = row_mm(h, cell.weight_hh.t(), cell.bias_hh)
    i_r, i_z, i_n = gi.chunk(3, dim=1)
    h_r, h_z, h_n = gh.chunk(3, dim=1)
    r = torch.sigmoid(i_r + h_r)
    z = torch.sigmoid(i_z + h_z)
    n = torch.tanh(i_n + r * h_n)
    return (1 - z) * n + z * h


def scale_down(x: Tensor, scale: float) -> Tensor:
    """``x / scale`` for a Python-number ``scale``; at inference as ``x * (1 / scale)``: torch divides by a scalar
    with a reciprocal multiply in its vectorised body but a true division in the scalar tail, so an element's bits
    would depend on where the tensor's end fell (it moved single-agent samples' forecasts by up to 7.5e-6 m)."""
    return x / scale if torch.is_grad_enabled() else x * (1.0 / scale)


def sigmoid(x: Tensor) -> Tensor:
    """``torch.sigmoid``; at inference on a flat copy padded to whole ``ROW_BLOCK``s: torch's vectorised body and
    its scalar tail round transcendental functions apart, so an element's bits would depend on where the tensor's
    end fell (a single agent's mode gates sit in the tail)."""
    if torch.is_grad_enabled():
        return torch.sigmoid(x)
    flat = x.reshape(-1)
    n = flat.numel()
    pad = (-n) % ROW_BLOCK
    if pad:
        flat = torch.cat((flat, flat.new_zeros(pad)))
    return torch.sigmoid(flat)[:n].view(x.shape)
