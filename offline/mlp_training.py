"""Training arithmetic of the ReLU network that :class:`onboard.low_level.planning.mlp.Mlp` evaluates: forward pass
with the activations kept, back-propagation, the input Jacobian and Adam, in numpy.

A 2 x 256 network has 67k weights and a training batch of tens to hundreds of rows: a handful
of (256 x 256) matrix products per step, well within numpy; a deep-learning framework would
add a dependency and a second copy of the inference code for nothing.

Weights are a dict ``W0, b0, ..., Wn, bn`` (``W_i`` shape (out, in)), the layout ``Mlp`` reads;
the network works on scaled numbers (the caller divides inputs by ``x_scale`` and multiplies
outputs by ``y_scale``, as ``Mlp`` does).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

Weights = dict[str, np.ndarray]


def layer_count(w: Weights) -> int:
    n = 0
    while f"W{n}" in w:
        n += 1
    return n


def init_weights(sizes: Sequence[int], rng: np.random.Generator) -> Weights:
    """He initialisation (variance 2 / fan-in keeps ReLU activations of order one), zero biases."""
    w: Weights = {}
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        w[f"W{i}"] = rng.standard_normal((n_out, n_in)) * math.sqrt(2.0 / n_in)
        w[f"b{i}"] = np.zeros(n_out)
    return w


def forward(w: Weights, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """``x`` (N, in) scaled -> output (N, out) and the activations (input, then each layer's
    output after its ReLU; the last layer has none)."""
    acts = [x]
    h = x
    last = layer_count(w) - 1
    for i in range(last + 1):
        h = h @ w[f"W{i}"].T + w[f"b{i}"]
        if i < last:
            h = np.maximum(h, 0.0)
        acts.append(h)
    return h, acts


def backward(w: Weights, acts: list[np.ndarray], g_out: np.ndarray) -> Weights:
    """Gradient of ``sum(g_out * output)`` with respect to every weight (``g_out`` (N, out) is
    dLoss/dOutput, already divided by the batch size if the loss is a mean)."""
    grads: Weights = {}
    g = g_out
    for i in range(layer_count(w) - 1, -1, -1):
        grads[f"W{i}"] = g.T @ acts[i]
        grads[f"b{i}"] = g.sum(axis=0)
        if i > 0:
            g = (g @ w[f"W{i}"]) * (acts[i] > 0.0)
    return grads


def input_jacobian(w: Weights, acts: list[np.ndarray]) -> np.ndarray:
    """d output / d input (N, out, in) at the rows of a forward pass (scaled units)."""
    n_layers = layer_count(w)
    jac = np.broadcast_to(w["W0"], (acts[0].shape[0],) + w["W0"].shape)
    for i in range(1, n_layers):
        jac = w[f"W{i}"] @ (jac * (acts[i] > 0.0)[:, :, None])
    return jac


def add_grads(a: Weights, b: Weights) -> Weights:
    return {k: a[k] + b[k] for k in a}


@dataclass
class Adam:
    """Adam (Kingma and Ba) with its usual constants."""

    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    t: int = 0
    m: Weights = field(default_factory=dict)
    v: Weights = field(default_factory=dict)

    def step(self, w: Weights, grads: Weights, rate: float) -> None:
        """Update ``w`` in place."""
        self.t += 1
        for k, g in grads.items():
            m = self.m.setdefault(k, np.zeros_like(g))
            v = self.v.setdefault(k, np.zeros_like(g))
            m *= self.beta1
            m += (1.0 - self.beta1) * g
            v *= self.beta2
            v += (1.0 - self.beta2) * g * g
            m_hat = m / (1.0 - self.beta1**self.t)
            v_hat = v / (1.0 - self.beta2**self.t)
            w[k] -= rate * m_hat / (np.sqrt(v_hat) + self.eps)


def fit(w: Weights, x: np.ndarray, y: np.ndarray, steps: int, rate: float, batch: int,
        rng: np.random.Generator) -> list[float]:
    """Least squares regression of ``y`` on ``x`` (scaled units) by Adam on random mini-batches;
    ``w`` updated in place; returns the mini-batch mean squared error of every step."""
    opt = Adam()
    history = []
    for _ in range(steps):
        idx = rng.integers(0, x.shape[0], batch)
        out, acts = forward(w, x[idx])
        diff = out - y[idx]
        history.append(float(np.mean(np.sum(diff * diff, axis=1))))
        opt.step(w, backward(w, acts, 2.0 * diff / batch), rate)
    return history
