"""The region types of the matching-entropy method (paper Sec. 3.2, Eqs. 9-12) as stored labels.

``regions.npy`` in a result folder holds these labels; ``regions.png`` shows them in the paper's
colours (Fig. 5). This module is the one table of both; it imports nothing heavy, so the report and
the demo can use it without loading the estimator.
"""

from __future__ import annotations

import numpy as np

OCCLUDING, OCCLUDED, TEXTURE, SMOOTH = 0, 1, 2, 3
#: ``REGION_NAMES[label]``.
REGION_NAMES = ("occluding", "occluded", "texture", "smooth")
#: Paper colours (Fig. 5), RGB per label: occluding red, occluded blue, texture yellow, smooth green.
REGION_COLOURS = np.array([(255, 0, 0), (0, 0, 255), (255, 255, 0), (0, 160, 0)], np.uint8)
