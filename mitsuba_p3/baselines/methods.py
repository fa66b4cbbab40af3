"""ProtoNets and MAML on the Conv-4 backbone, as pure functions of parameters and a task.

A *task* is (support images, support labels, query images, query labels, n_way)
with labels 0..n_way-1. Each method has ``init(key, resolution)``,
``task_loss(params, task) -> (loss, accuracy)`` for meta-training and
``predict(params, support, labels, queries, n_way) -> (Q, n_way)`` probabilities.

- **ProtoNets** (Snell et al. 2017): class prototypes are the mean support
  embeddings; logits are negative squared Euclidean distances to them.
- **MAML** (Finn et al. 2017), with the paper's miniImageNet numbers: inner
  learning rate 0.01, 5 inner steps in meta-training and 10 at test. It is
  *first-order* by default (the meta-gradient drops the inner loop's second
  derivatives: about 3x cheaper on the 2-core machine, and Finn et al. report
  nearly the same accuracy); ``second_order=True`` differentiates through the
  inner loop. Its linear head has ``MAX_WAY`` outputs; an N-way task uses the first N.
"""
from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from . import conv4

MAX_WAY = 10


def _cross_entropy(logits, labels):
    log_p = jax.nn.log_softmax(logits)
    return -jnp.mean(jnp.take_along_axis(log_p, labels[:, None], axis=1))


def _accuracy(logits, labels):
    return jnp.mean(jnp.argmax(logits, axis=1) == labels)


@dataclass(frozen=True)
class ProtoNets:
    name: str = "protonets"

    def init(self, key, resolution: int):
        return {"backbone": conv4.init_params(key)}

    def embed(self, params, images):
        """(B, R, R, 3) images -> (B, F) embeddings: the Conv-4's flattened last map."""
        return conv4.embed(params["backbone"], images)

    def logits(self, params, support, labels, queries, n_way: int):
        embedded = self.embed(params, jnp.concatenate([support, queries]))
        s, q = embedded[:len(support)], embedded[len(support):]
        one_hot = jax.nn.one_hot(labels, n_way)
        prototypes = one_hot.T @ s / one_hot.sum(axis=0)[:, None]
        # ||q - p||^2 expanded: a matmul instead of a (Q, N, F) broadcast
        return -(jnp.sum(q * q, axis=1)[:, None] - 2.0 * q @ prototypes.T + jnp.sum(prototypes ** 2, axis=1)[None])

    def task_loss(self, params, task):
        support, labels, queries, query_labels, n_way = task
        logits = self.logits(params, support, labels, queries, n_way)
        return _cross_entropy(logits, query_labels), _accuracy(logits, query_labels)

    def predict(self, params, support, labels, queries, n_way: int):
        return jax.nn.softmax(self.logits(params, support, labels, queries, n_way))


@dataclass(frozen=True)
class MAML:
    name: str = "maml"
    inner_lr: float = 0.01
    train_steps: int = 5
    test_steps: int = 10
    second_order: bool = False

    def init(self, key, resolution: int):
        k_backbone, k_head = jax.random.split(key)
        features = conv4.feature_size(resolution)
        return {"backbone": conv4.init_params(k_backbone),
                "head": {"w": jax.random.normal(k_head, (features, MAX_WAY)) * jnp.sqrt(1.0 / features),
                         "b": jnp.zeros(MAX_WAY)}}

    def _logits(self, params, images, n_way: int):
        features = conv4.embed(params["backbone"], images)
        return (features @ params["head"]["w"] + params["head"]["b"])[:, :n_way]

    def adapt(self, params, support, labels, n_way: int, steps: int):
        """``steps`` gradient steps on the support loss (the inner loop)."""
        def support_loss(p):
            return _cross_entropy(self._logits(p, support, n_way), labels)

        for _ in range(steps):
            grads = jax.grad(support_loss)(params)
            if not self.second_order:
                grads = jax.lax.stop_gradient(grads)
            params = jax.tree_util.tree_map(lambda p, g: p - self.inner_lr * g, params, grads)
        return params

    def task_loss(self, params, task):
        support, labels, queries, query_labels, n_way = task
        adapted = self.adapt(params, support, labels, n_way, self.train_steps)
        logits = self._logits(adapted, queries, n_way)
        return _cross_entropy(logits, query_labels), _accuracy(logits, query_labels)

    def predict(self, params, support, labels, queries, n_way: int):
        adapted = self.adapt(params, support, labels, n_way, self.test_steps)
        return jax.nn.softmax(self._logits(adapted, queries, n_way))


METHODS = {"protonets": ProtoNets, "maml": MAML}
