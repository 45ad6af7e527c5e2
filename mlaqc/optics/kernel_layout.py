"""The compiled tracer's data layout: its modes, the slots of its settings vector and the rows of its tables.

Shared by the kernels (raytrace_kernels and the helpers it inlines) and by FastCamera, which packs the
camera into these tables; plain constants, no Numba.
"""

from __future__ import annotations

import numpy as np


# Modes of the kernel.
IMAGE_SIDE, POINT, OBJECT_SIDE = 0, 1, 2
# Slots of the scalar parameter vector.
(S_MODE, S_X0, S_X1, S_Y0, S_Y1, S_ZSTART, S_ZEXIT, S_RPUPIL, S_PX, S_PY,
 S_C1, S_C2, S_T, S_N, S_RIM2, S_FRES, S_ZOBJ, S_TEXHX, S_TEXHY,
 S_P, S_AX0, S_AY0, S_ROWS, S_COLS, S_ZFRONT, S_NMLA, S_CLEAR, S_SHIFTX,
 S_ZMLA, S_SHIFTY, S_ZSENS, S_PIX, S_SX0, S_SY0, S_W, S_H, S_INVP, S_INVPIX,
 # the low-discrepancy sampler: on/off, the job's block of cells (first row and column, width, cells) and
 # first point index, padded cells per row, and the MLA frame's 2 x 2 map to the start plane
 S_SOBOL, S_CR0, S_CC0, S_CBW, S_CB, S_J0, S_PCOLS, S_R00, S_R01, S_R10, S_R11,
 S_INVKR, S_SQUARE, S_SQW,
 # half the black matrix' width (mm; sag-intersection boundaries are a kernel of their own, kernel_sag)
 S_HALFBM,
 # circle apertures: radius^2, clear gaps (per-cell reach: the `circ` table)
 S_RCIRC2, S_CLEARGAP,
 # 1: re-traces skip candidates that provably cannot win (pair clearances); 0: every doubted ray scans
 # them all (the exhaustive path, which tests hold the pruned one to, image for image)
 S_PRUNE,
 # run-time switches (one kernel serves both sides: each pass they change is inlined once per side and chosen
 # per block of rays, which costs nothing measurable): a textured scene, a global MLA rotation
 S_TEXTURE, S_GROT, S_COUNT) = range(59)
# Rows of the per-block scratch table `g`: the gathered parameters of each ray's lens (tab rows 0..6), its
# current hit and direction in the lens frame, the distance t to it (NaN on a miss), and its pixel.
# Sag-intersection mode also gathers the lens' front and rear margins (G_MF, G_MR) and design centre (G_CX, G_CY).
G_FX, G_FY, G_DX, G_DY, G_C1, G_C2, G_ZR, G_HX, G_HY, G_HZ, G_LL, G_LM, G_LN, G_T, G_ROW, G_COL, G_MF, G_MR, G_CX, G_CY, G_COUNT = range(21)
# Rows of the per-lens `margins` table of sag-intersection mode (kernel_sag): front and rear margins (mm,
# raytrace.MicrolensArray.boundary_margins_mm), design centre x, y (mm).
T_MARGIN_FRONT, T_MARGIN_REAR, T_GX, T_GY = 0, 1, 2, 3
# Rows of the per-lens `circ` table of circle apertures: design centre x, y (mm), (radius + reach)^2 (mm^2),
# the edge distance (mm) within which a neighbour's circle can hold a hit (circle_clearance_mm).
C_GX, C_GY, C_REACH2, C_CLEAR = 0, 1, 2, 3


BLOCK = 256  # rays per block: every pass works on a block held in L1
NO_TEXTURE = np.ones((1, 1))  # the texture argument of a scene without one (S_TEXTURE 0: never read)
