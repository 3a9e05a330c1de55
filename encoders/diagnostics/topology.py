"""Topology: do the latents of a 2-D grid of states still form a grid?

The latents of a ``grid_size`` x ``grid_size`` grid over two state dimensions (the others
at the centre of the state box) are embedded in 2-D with isomap; a reward encoder that
keeps the task's topology gives a flat, unfolded sheet coloured smoothly by each
coordinate. The env is reset first, so nothing an earlier analysis left (fetch_push: the
arm) is in the pictures.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from scipy.spatial import procrustes
from sklearn.manifold import Isomap, trustworthiness

from encoders.base import RewardEncoder
from encoders.diagnostics.common import (
    ControllableEnv,
    Progress,
    bounds,
    encode_all,
    fresh_reset,
    render_states,
)


def default_grid_dims(env: ControllableEnv) -> tuple[int, int]:
    """The first two state dimensions whose bounds are not a single value."""
    low, high = bounds(env)
    dims = [i for i in range(len(low)) if high[i] > low[i]]
    if len(dims) < 2:
        raise ValueError("the env's state box has fewer than two non-degenerate dimensions")
    return dims[0], dims[1]


def grid_topology(
    env: ControllableEnv,
    encoders: Mapping[str, RewardEncoder],
    grid_size: int = 15,
    dims: Sequence[int] | None = None,
    n_neighbors: int = 10,
    seed: int = 0,
    progress: bool = True,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Isomap of the latents of a state grid over ``dims`` (default ``default_grid_dims``),
    rendered after ``env.reset(seed=seed)``.

    Returns (summary rows ``encoder, metric, value`` with ``procrustes_disparity`` between
    the embedding and the reached grid, 0 = the same up to rotation and scale, and
    ``trustworthiness`` of the embedding's ``n_neighbors`` neighbourhoods, 1 = all true
    grid neighbours; embedding rows ``encoder, i, j, state_a, state_b, iso_x, iso_y``).
    """
    low, high = bounds(env)
    a, b = default_grid_dims(env) if dims is None else (int(dims[0]), int(dims[1]))
    for d in (a, b):
        if not 0 <= d < len(low):
            raise ValueError(f"grid dims must be in [0, {len(low)}), got {d}")
    if a == b:
        raise ValueError(f"grid dims must differ, got {a} and {b}")
    if n_neighbors < 1 or grid_size < 3 or grid_size * grid_size <= 2 * n_neighbors:
        raise ValueError(
            f"need grid_size >= 3 and grid_size^2 > 2 * n_neighbors, got grid_size={grid_size}, "
            f"n_neighbors={n_neighbors}"
        )
    ii, jj = np.meshgrid(np.arange(grid_size), np.arange(grid_size), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    targets = np.tile((low + high) / 2, (len(ii), 1))
    targets[:, a] = np.linspace(low[a], high[a], grid_size)[ii]
    targets[:, b] = np.linspace(low[b], high[b], grid_size)[jj]
    fresh_reset(env, seed)
    bar = Progress("topology grid states", len(targets), progress)
    reached, images = render_states(env, targets, bar)
    grid = reached[:, [a, b]]
    summary, embedded = [], []
    for name, z in encode_all(encoders, images).items():
        iso = Isomap(n_neighbors=n_neighbors, n_components=2).fit_transform(z)
        _, _, disparity = procrustes(grid, iso)
        trust = trustworthiness(grid, iso, n_neighbors=n_neighbors)
        summary.append({"encoder": name, "metric": "procrustes_disparity", "value": disparity})
        summary.append({"encoder": name, "metric": "trustworthiness", "value": float(trust)})
        embedded.append(
            pd.DataFrame(
                {
                    "encoder": name,
                    "i": ii,
                    "j": jj,
                    "state_a": grid[:, 0],
                    "state_b": grid[:, 1],
                    "iso_x": iso[:, 0],
                    "iso_y": iso[:, 1],
                }
            )
        )
    return pd.DataFrame(summary), pd.concat(embedded, ignore_index=True)
