"""The material's moves that jump rather than update: along the colour/weight ridge, and between kinds.

The Gibbs update of :mod:`mitsuba_p3.infer.material_moves` draws the colour given the weights and the
weights given the colour, each from a narrow conditional once the likelihood is sharp. Two directions
it cannot cross in one step get a move of their own here:

- **the ridge** (:meth:`MaterialJumps.ridge_move`): the image sees the colour only through c k_a and
  c k_d, so (c s, k_a / s, k_d / s) renders alike for every s > 0; the move walks along s under the
  prior, with no render;
- **the kind** (:meth:`MaterialJumps._kind_jump`): a new shininess drawn from its prior (broad or tight
  highlights: matte or shiny), the weights drawn from their conditional at the new bases, accepted by
  the Hastings ratio of that independence proposal.

:class:`MaterialJumps` is the base of :class:`~mitsuba_p3.infer.material_moves.MaterialMoves` and
uses the same members of the posterior core (``prior``, ``params``, ``_image``) and of the Gibbs update
(``_gram_statistics``, ``_gram``, ``_weight_coordinates``, ``_weights_conditional``, ``_independence_mh``).
"""
from __future__ import annotations

from ..space import SLICES

# The ridge move's step: log s ~ N(0, RIDGE_STEP^2), a fifth of an e-fold of the colour's brightness.
RIDGE_STEP = 0.2


class MaterialJumps:
    """The ridge move and the material kind's jump of a posterior core (the module docstring)."""

    def ridge_move(self, key, state, log_prior=None, step: float = RIDGE_STEP):
        """An MH move along the colour/weight ridge; no render.

        The image sees the colour c only through the products c k_a and c k_d (the
        specular lobe is white), so the scene (c s, k_a / s, k_d / s) renders exactly
        like (c, k_a, k_d) for any s > 0, as long as no channel of c is clipped at 1.
        Along that ridge the posterior is the prior's, and the material update, which
        draws the colour given the weights and then the weights given the colour, crawls
        along it in tiny steps once the likelihood is sharp (each conditional is narrow):
        runs with different seeds then sit at different points of the same ridge. This
        move proposes log s ~ N(0, ``step``^2) and accepts with the prior ratio times the
        Jacobian s (c scales 3 coordinates by s, k_a and k_d two by 1/s; the affine maps to
        z cancel); a proposal or state with a channel of c above 1 is rejected (there the
        render would change), which keeps detailed balance. ``state.logdensity`` changes by
        the prior's difference only; ``log_prior`` defaults to :meth:`Prior.log_prob`."""
        import jax
        import jax.numpy as jnp

        log_prior = log_prior or self.prior.log_prob
        k_step, k_accept = jax.random.split(key)
        z = state.position
        x = self.prior.constrain(z)
        log_s = step * jax.random.normal(k_step)
        s = jnp.exp(log_s)
        new = z
        for name, factor in (("colour", s), ("ambient", 1.0 / s), ("diffuse", 1.0 / s)):
            g = self.prior.gmms[name]
            value = x[name] if name == "colour" else x[name][..., None]
            new = new.at[SLICES[name]].set((value * factor - g.mean) / g.std)
        new_colour = x["colour"] * s
        inside = (jnp.max(x["colour"]) <= 1.0) & (jnp.max(new_colour) <= 1.0)
        delta = log_prior(new) - log_prior(z)
        accept = inside & (jnp.log(jax.random.uniform(k_accept)) < delta + log_s)
        return type(state)(jnp.where(accept, new, z), jnp.where(accept, state.logdensity + delta, state.logdensity))

    def _jump_proposal(self, key, position):
        """The kind's jump's new shininess (:meth:`_kind_jump`): ``position`` with it drawn from its prior,
        from the key :meth:`_kind_jump` is given."""
        import jax
        import jax.numpy as jnp

        k_component, k_noise, _, _ = jax.random.split(key, 4)
        g = self.prior.gmms["shininess"]
        loc, std = float(g.mean[0]), float(g.std[0])
        means, sds = jnp.asarray(g.means[:, 0]), jnp.sqrt(jnp.asarray(g.variances[:, 0]))
        component = jax.random.categorical(k_component, jnp.log(jnp.asarray(g.weights)))
        alpha = means[component] + sds[component] * jax.random.normal(k_noise)
        return position.at[SLICES["shininess"].start].set((alpha - loc) / std)

    def _kind_jump(self, key, state, bases, gram, statistics, observation, target, new_bases=None):
        """The material kind's jump: a new shininess drawn from its prior (a mixture of the fitted
        materials' components: broad highlights and tight ones), the weights (k_a, k_d, k_s) drawn from
        their conditional at the new shininess's bases (one render) given the colour, accepted with the
        Hastings ratio of that independence proposal, whose reverse density takes the weights'
        conditional at the current bases. The walk moves the shininess only locally and the weights
        follow it only through the Gibbs update, so a run whose particles settled on one kind of
        highlight could keep them there; this move proposes the other kind whole. Returns (state, accepted, bases, gram and Gram
        statistics (:meth:`_gram_statistics`) of the state kept)."""
        import jax
        import jax.numpy as jnp

        _, _, k_weights, k_accept = jax.random.split(key, 4)
        g = self.prior.gmms["shininess"]
        s = SLICES["shininess"].start
        loc, std = float(g.mean[0]), float(g.std[0])

        def log_q_alpha(z_alpha):    # the prior's density in the natural unit (its Jacobian std cancels)
            return g.log_prob((loc + std * z_alpha)[None])

        position = state.position
        moved = self._jump_proposal(key, position)
        if new_bases is None:                                                # the same pose: the same objects
            new_bases, _ = self._image(moved, observation, bases=True)
        colour = self.params(position)["colour"]
        new_statistics = self._gram_statistics(new_bases, target[3], observation, position)
        new_gram = self._gram(new_statistics, target[0], colour)
        dims, w_loc, w_std = self._weight_coordinates()
        old, new = self._weights_conditional(gram, colour), self._weights_conditional(new_gram, colour)
        weights = new.draw(k_weights)
        new_position = moved.at[dims].set((weights - w_loc) / w_std)
        log_q_ratio = (log_q_alpha(position[s]) + old.log_q(w_loc + w_std * position[dims])
                       - log_q_alpha(new_position[s]) - new.log_q(weights))
        state, accepted = self._independence_mh(k_accept, state, new_position, new_bases, log_q_ratio,
                                                observation, target)
        keep = lambda new, old: jnp.where(accepted, new, old)  # noqa: E731
        return (state, accepted, keep(new_bases, bases), keep(new_gram, gram),
                jax.tree_util.tree_map(keep, new_statistics, statistics))
