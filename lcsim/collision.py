"""Exact collision test for oriented rectangles (separating-axis theorem).

The simulator only calls it on candidate pairs: a vehicle and its leader (the nearest vehicle ahead
in any lane its body overlaps) when their gap along x is under a metre, so no all-pairs work is done.
"""

from __future__ import annotations

import numpy as np


def obb_overlap(xa: np.ndarray, ya: np.ndarray, yawa: np.ndarray, la: np.ndarray, wa: np.ndarray,
                xb: np.ndarray, yb: np.ndarray, yawb: np.ndarray, lb: np.ndarray, wb: np.ndarray) -> np.ndarray:
    """Exact overlap of oriented rectangles (centre, yaw, length, width), elementwise over shape (K,).

    Separating-axis theorem: two convex rectangles are disjoint iff their projections are disjoint on
    one of the four edge normals. Touching edges count as overlap.
    """
    dx, dy = xb - xa, yb - ya
    ca, sa, cb, sb = np.cos(yawa), np.sin(yawa), np.cos(yawb), np.sin(yawb)
    hla, hwa, hlb, hwb = 0.5 * la, 0.5 * wa, 0.5 * lb, 0.5 * wb
    # The four edge normals stacked on a leading axis: one pass instead of a loop over axes.
    ux = np.stack(np.broadcast_arrays(ca, -sa, cb, -sb))
    uy = np.stack(np.broadcast_arrays(sa, ca, sb, cb))
    dist = np.abs(dx * ux + dy * uy)
    ra = hla * np.abs(ca * ux + sa * uy) + hwa * np.abs(-sa * ux + ca * uy)
    rb = hlb * np.abs(cb * ux + sb * uy) + hwb * np.abs(-sb * ux + cb * uy)
    return (dist <= ra + rb).all(axis=0)
