"""One map layer prepared for fast drawing by a ``logpipe.raster.rasteriser.Rasteriser``.

Per raster the cost is Python and NumPy call overhead plus OpenCV's per-polyline work, not arithmetic. So
a layer's vertices (``MapStore.render_layer``: lanes chained with their unique successors, then cut into
cell-sized chunks) are kept in grid-band order, a window being ~2 contiguous slices, each transformed in place
into a reused int32 fixed-point buffer (``shift`` fractional bits, OpenCV's sub-pixel drawing) by one matrix
product; the chunks are ready-made views of that buffer. Layers without features cost nothing per raster.
"""

from __future__ import annotations

import numpy as np

from logpipe.maps.grid_index import BandOrder, Layer
from logpipe.types import NDArrayFloat, NDArrayInt32

BAND_ROWS = 8
"""Grid rows (32 m) per band of the vertex order: a 100 m window, rotated, spans ~6 rows, so it reads ~1.5
slices; taller bands read more vertices in vain, shorter ones more slices."""


class PreparedLayer:
    """One layer prepared for drawing by one rasteriser. Memory is of the order of the layer's own (vertex
    buffers, one view object per chunk); no pixels are cached, so it stays small for city-sized maps.

    Vertices are stored in ``BandOrder`` (a window is ~2 contiguous slices, each transformed in place by
    one product) while chunks are still drawn in layer order, the reference's: ``views[i]`` is layer
    chunk ``i`` wherever it sits in the buffer.

    Attributes:
        band: the band order of the layer's chunks.
        pix: (N, 2) int32 fixed-point pixel coordinates of the vertices, band order; only the chunks of
            the window being drawn are valid (every render rewrites them).
        homog: (N, 3) the vertices as (x, y, 1), band order.
        offsets: (F + 1,) vertex offset of each band position, a Python list (indexed per slice).
        boxes: (F, 4) bounding-box centre (x, y) and half-size (x, y) of each band position, metres.
        views: layer chunk ``i`` as its slice of ``pix``, made once: slicing per chunk and render costs
            more than the rest of the per-chunk work.
    """

    def __init__(self, layer: Layer, band_rows: int) -> None:
        self.band = BandOrder(layer, band_rows)
        order = self.band.order
        counts = layer.counts[order]
        offsets = np.zeros(len(order) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        n = int(offsets[-1])
        # Vertex j of position p comes from layer vertex layer.offsets[order[p]] + (j - offsets[p]).
        src = np.repeat(layer.offsets[order] - offsets[:-1], counts) + np.arange(n, dtype=np.int64)
        self.homog: NDArrayFloat = np.concatenate([layer.points[src], np.ones((n, 1))], axis=1)
        self.pix: NDArrayInt32 = np.zeros((n, 2), dtype=np.int32)
        self.offsets: list[int] = offsets.tolist()
        lo, hi = layer.lo[order], layer.hi[order]
        self.boxes: NDArrayFloat = np.concatenate([(lo + hi) / 2.0, (hi - lo) / 2.0], axis=1)
        pix, o = self.pix, self.offsets
        self.views: list[NDArrayInt32] = [pix[o[p] : o[p + 1]] for p in self.band.position.tolist()]
