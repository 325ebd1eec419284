"""``row_mm``: a row's product never depends on the other rows, on where it sits, or on whether its block was
multiplied in place (whole blocks of a contiguous, aligned input) or from a zero-padded copy."""

from __future__ import annotations

import pytest
import torch

from logpipe.model.training.row_blocks import ROW_BLOCK, row_mm


@pytest.mark.parametrize("width", [2, 67, 131, 195])
@pytest.mark.parametrize("cols", [1, 2, 64, 256])
def test_every_row_gets_the_bits_it_gets_alone(width: int, cols: int) -> None:
    gen = torch.Generator().manual_seed(width * 1000 + cols)
    rows = 2 * ROW_BLOCK + 37  # two whole blocks multiplied in place, and a part-block copied
    x = torch.randn(rows, width, generator=gen)
    w = torch.randn(width, cols, generator=gen)
    bias = torch.randn(cols, generator=gen)
    assert x.is_contiguous() and x.data_ptr() % 64 == 0  # the in-place path is the one under test
    with torch.inference_mode():
        together = row_mm(x, w, bias)
        # the same rows where the in-place path cannot run: a strided view, and a view 4 bytes off alignment
        strided = row_mm(x.t().contiguous().t(), w, bias)
        store = torch.empty(rows * width + 1)
        shifted_x = store[1:].view(rows, width)
        shifted_x.copy_(x)
        shifted = row_mm(shifted_x, w, bias)
        picked = [0, 1, ROW_BLOCK - 1, ROW_BLOCK, 2 * ROW_BLOCK - 1, 2 * ROW_BLOCK, rows - 1]
        alone = torch.cat([row_mm(x[i : i + 1], w, bias) for i in picked])
        offset = torch.cat([row_mm(x[i : i + 5], w, bias)[:1] for i in picked])  # leading other rows' blocks
    assert torch.equal(together, strided) and torch.equal(together, shifted)
    assert torch.equal(together[picked], alone) and torch.equal(together[picked], offset)
    torch.testing.assert_close(together, x @ w + bias, rtol=1e-5, atol=1e-4)
