"""Inference of a small ReLU network (the neural Zero Dynamics Policy, thesis 2733-2745).

The thesis's policy is a 2 x 256 ReLU network evaluated at 1 kHz. Here the weights
come as arrays (the caller reads the ``.npz`` file: this package does no I/O):

- ``W0``, ``b0``, ``W1``, ``b1``, ..., ``Wn``, ``bn``: layer ``i`` maps
  ``x -> W_i x + b_i`` (``W_i`` shape (out, in)), ReLU after every layer but the last;
- ``x_scale`` (in,): inputs are divided by it first; ``y_scale`` (out,): outputs are
  multiplied by it last (so the network works on numbers of order one).

For the ZDP the input is the error of the predicted impact state to the reference,
``(x, y, vx, vy)`` [m, m/s], and the output the impact attitude ``(a_x, a_y)``
(:mod:`onboard.low_level.planning.zdp`). ``services/cli/train_zdp.py`` trains and writes the weights.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np


class Mlp:
    def __init__(self, weights: Mapping[str, np.ndarray]) -> None:
        layers = []
        i = 0
        while f"W{i}" in weights:
            w = np.ascontiguousarray(weights[f"W{i}"], dtype=float)
            b = np.ascontiguousarray(weights[f"b{i}"], dtype=float).reshape(-1)
            if w.ndim != 2 or b.shape[0] != w.shape[0]:
                raise ValueError(f"layer {i}: W {w.shape} and b {b.shape} do not match")
            if layers and layers[-1][0].shape[0] != w.shape[1]:
                raise ValueError(f"layer {i} expects {w.shape[1]} inputs, previous gives {layers[-1][0].shape[0]}")
            layers.append((w, b))
            i += 1
        if not layers:
            raise ValueError("no layers (W0, b0, ...) in the weights")
        self.layers = layers
        self.n_in = layers[0][0].shape[1]
        self.n_out = layers[-1][0].shape[0]
        self.x_scale = np.asarray(weights.get("x_scale", np.ones(self.n_in)), dtype=float).reshape(-1)
        self.y_scale = np.asarray(weights.get("y_scale", np.ones(self.n_out)), dtype=float).reshape(-1)
        if self.x_scale.shape != (self.n_in,) or self.y_scale.shape != (self.n_out,):
            raise ValueError("x_scale / y_scale do not match the layer sizes")
        if not all(np.isfinite(a).all() for wb in layers for a in wb):
            raise ValueError("non-finite weights")
        if np.any(self.x_scale <= 0):
            raise ValueError("x_scale must be positive")
        self._inv_x = 1.0 / self.x_scale

    def forward(self, x: np.ndarray) -> np.ndarray:
        """Batched: ``x`` (N, in) -> (N, out)."""
        h = np.asarray(x, dtype=float) * self._inv_x
        last = len(self.layers) - 1
        for i, (w, b) in enumerate(self.layers):
            h = h @ w.T + b
            if i < last:
                np.maximum(h, 0.0, out=h)
        return h * self.y_scale

    def __call__(self, x: Sequence[float]) -> tuple[float, ...]:
        """One input vector -> output tuple."""
        h = np.asarray(x, dtype=float) * self._inv_x
        last = len(self.layers) - 1
        for i, (w, b) in enumerate(self.layers):
            h = w @ h + b
            if i < last:
                np.maximum(h, 0.0, out=h)
        return tuple(float(v) for v in h * self.y_scale)

    def as_arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for i, (w, b) in enumerate(self.layers):
            out[f"W{i}"] = w
            out[f"b{i}"] = b
        out["x_scale"] = self.x_scale
        out["y_scale"] = self.y_scale
        return out
