"""The moves that need no pose change: the material's Gibbs update (its kind's jump and the colour ridge:
:mod:`mitsuba_p3.infer.material_jumps`).

Given the pose, the class and the shininess, one render of the *material bases* (A, D, S, F: ambient,
diffuse, specular and the rest of the scene; the renderers' ``render_bases``) makes the image an explicit
function of the material,

    I = clip(c (k_a A + k_d D) + k_s S + F),

affine in the colour c given the weights (k_a, k_d, k_s) and affine in the weights given the colour. Under
the Gaussian part of the likelihood and the GMM priors each conditional is then a Gaussian mixture
(:class:`~mitsuba_p3.infer.material_conditional.MixtureConditional`); a draw from it is an independence proposal, accepted by MH with the exact
(tempered) log joint computed from the bases without another render, so clipping, the noise's outliers and
the neural term stay exact. The precision-weighted inner products of the bases (:meth:`MaterialMoves._gram`)
are all either conditional needs; the shading fields (:mod:`mitsuba_p3.fit.fields`) take their low-rank part
off them.

:class:`MaterialMoves` is a mixin of :class:`mitsuba_p3.infer.model.PosteriorCore`: it uses the core's
``prior``, likelihood ``config``, ``params`` (z -> the renderer contract), ``_image`` (a render or the bases
of z for an observation, and the pixels its object covers), ``_score`` and ``window_log_term``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import small_linalg
from ..fit.fields import COLOURED
from ..space import SLICES
from .likelihood import fields_form, fields_masks, fields_regions, whiten
from .material_conditional import MixtureConditional
from .material_jumps import MaterialJumps

class ScoredState(NamedTuple):
    """An MH state (position, log density) that also carries its log likelihood, which the material's
    independence tests update as they accept (:meth:`MaterialMoves.scored_material_move`)."""
    position: object
    logdensity: object
    loglikelihood: object


class MaterialMoves(MaterialJumps):
    """The material's moves of a posterior core (see the module docstring): :meth:`material_move` and
    :meth:`scored_material_move` (colour, then weights; optionally the kind's jump first), and from
    :class:`~mitsuba_p3.infer.material_jumps.MaterialJumps` the ridge move and the kind's jump."""

    def material_move(self, key, state, observation, tempering=1.0, log_prior=None):
        """Metropolis-within-Gibbs update of the materials of one chain's state: colour, then (k_a, k_d, k_s).

        One render of the material bases (:meth:`render_bases` of the renderers) makes
        the image an explicit function of the materials at the current pose, class and
        shininess: ``clip(c (k_a A + k_d D) + k_s S + F)``. Before clipping it is affine
        in the colour given the weights, and affine in the weights given the colour.
        With the Gaussian form of the colour likelihood and the GMM priors, each
        conditional is then a Gaussian mixture; a draw from it is an independence
        proposal, accepted by MH with the exact log joint, computed from the bases
        without another render (clipping, truncation and the neural term included).
        Returns (new state, both accepted).

        For a tempered target ``log_prior(z) + tempering * log p(I | z)`` (sequential Monte Carlo),
        pass ``tempering`` and the prior (default: :meth:`Prior.log_prob`); ``state.logdensity`` is
        then that target's value.
        """
        state, accepted, _, _ = self.scored_material_move(key, state, observation, tempering, log_prior)
        return state, accepted

    def material_renders(self, key, position, observation, jump: bool = False) -> tuple:
        """What :meth:`scored_material_move` renders, given the move's ``key``: the material bases of
        ``position`` and the pixels its object covers, and with ``jump`` the bases of the kind's jump
        proposal (:meth:`_jump_proposal`; else None). A batched sampler renders these for every
        particle in one callback and moves the particles in chunks (``rendered``)."""
        import jax

        bases, objects = self._image(position, observation, bases=True)
        if not jump:
            return bases, objects, None
        k_jump = jax.random.split(key, 3)[2]
        return bases, objects, self._image(self._jump_proposal(k_jump, position), observation, bases=True)[0]

    def scored_material_move(self, key, state, observation, tempering=1.0, log_prior=None, jump: bool = False,
                             rendered: tuple | None = None, loglikelihood=None):
        """:meth:`material_move`, also returning log p(I | z) of the new state, computed from the
        bases it rendered: a tempered sampler needs the likelihood apart from the prior, and this
        saves it a render per move. With ``jump``, the material kind's jump (:meth:`_kind_jump`, one
        more render) comes first. ``rendered``: :meth:`material_renders` of the same key and position,
        made beforehand (then this move renders nothing). ``loglikelihood``: the state's log likelihood where
        the caller has it (a sampler's cache): the move then returns the one its MH tests computed for the
        state kept (that, where every proposal was rejected) and scores no render after them. Returns (state,
        colour and weights accepted, log likelihood, jump accepted (False without ``jump``))."""
        import jax
        import jax.numpy as jnp

        k_colour, k_weights, k_jump = jax.random.split(key, 3)
        kind = type(state)
        if loglikelihood is not None:
            state = ScoredState(state.position, state.logdensity, loglikelihood)
        bases, objects, jump_bases = rendered or self.material_renders(key, state.position, observation, jump)
        statistics = self._gram_statistics(bases, objects, observation, state.position)
        gram = self._gram(statistics, tempering, self.params(state.position)["colour"])
        # the material moves leave the pose, so the window's term (mitsuba_p3.infer.window) and the object's
        # pixels are the state's throughout
        term = self.window_log_term(state.position, observation)
        target = (tempering, log_prior or self.prior.log_prob, term, objects)
        jumped = jnp.asarray(False)
        if jump:
            state, jumped, bases, gram, statistics = self._kind_jump(k_jump, state, bases, gram, statistics,
                                                                     observation, target, jump_bases)
        # (tinted fields load on the colour: the weights' conditional takes the Gram of the colour kept)
        state, colour_ok, gram = self._colour_move(k_colour, state, bases, gram, observation, target, statistics)
        state, weights_ok = self._weights_move(k_weights, state, bases, gram, observation, target)
        if isinstance(state, ScoredState):
            loglik = state.loglikelihood
        else:
            loglik = self._score(self._image_from_bases(bases, state.position), objects, observation,
                                 state.position) + term
        return kind(state.position, state.logdensity), colour_ok & weights_ok, loglik, jumped

    @property
    def _tinted(self) -> bool:
        """Whether the likelihood's shading fields load on the object's colour (their Gram then depends on it)."""
        return self.config.fields is not None and self.config.fields_channels in COLOURED

    def _gram_statistics(self, bases, objects, observation, position=None) -> tuple:
        """What :meth:`_gram` needs of the bases that the colour leaves alone: the inner products of the
        bases A, D, S and the residual r = I_obs - F, all channels' (4, 3, 4, 3), and under shading fields
        the vectors' field statistics (:func:`~mitsuba_p3.fit.fields.field_statistics` of the regions of
        the pose: its object's pixels ``objects``, the floor its shadow changes, the rest of the floor);
        None without fields. Computed once per bases: the tinted fields' colour move takes a second Gram
        at the proposal's colour from the same statistics. Fields on the object's normals take them from
        ``position``'s pose (:meth:`normals`)."""
        import jax.numpy as jnp

        from ..fit.fields import field_statistics, monomials

        vectors = jnp.concatenate([bases[..., :3, :], (observation["image"] - bases[..., 3, :])[..., None, :]],
                                  axis=-2)                                          # (h, w, 4, 3)
        if self.config.spectral:
            # the spectral form's quadratic is that of whitened images (linear)
            vectors = jnp.moveaxis(whiten(jnp.moveaxis(vectors, -2, 0), observation, self.config), 0, -2)
        flat = vectors.reshape(-1, 12)                                              # (pixels, 4 x 3)
        full = (flat.T @ flat).reshape(4, 3, 4, 3)                                  # one matmul: XLA's fast path
        if self.config.fields is None:
            return full, None
        masks = fields_masks(bases[..., 3, :], objects, observation["empty"], fields_regions(self.config))
        if self.config.fields_object == "normals":
            from ..fit.irradiance import region_bases, statistics

            normal_bases = region_bases(self.normals(position, observation), masks.shape, jnp)
            return full, statistics(jnp.moveaxis(vectors, -2, 0), masks, normal_bases, xp=jnp)
        basis = monomials(*vectors.shape[:2], self.config.fields_degree)
        return full, field_statistics(jnp.moveaxis(vectors, -2, 0), masks, basis, xp=jnp)   # b: (4, R, k, 3)

    def _gram(self, statistics, tempering, colour=None):
        """The tempered precision-weighted inner products of the bases A, D, S and the residual
        r = I_obs - F, each taken in one colour channel, from :meth:`_gram_statistics`: both material
        conditionals need only these. (3, 4, 4) per channel where the noise keeps the channels apart;
        (3, 3, 4, 4) [c, c', i, j] where it couples them (shading fields shared across channels,
        :mod:`mitsuba_p3.fit.fields`; tinted ones load on the object's ``colour``)."""
        import jax.numpy as jnp

        full, fields = statistics
        precision = tempering * self.config.power / self.config.sigma ** 2
        if self.config.spectral:    # the whitened vectors' quadratic is at precision power
            precision = tempering * self.config.power
        # the Gaussian part of the likelihood (outliers are left to the MH test)
        gram = jnp.einsum("icjc->cij", full)
        if self.config.fields is not None:
            correction = self._fields_correction(fields, colour)                      # (3, 3, 4, 4)
            if self.config.fields_channels == "independent":
                gram = gram - jnp.einsum("ccij->cij", correction)
            else:
                gram = jnp.einsum("cd,cij->cdij", jnp.eye(3, dtype=gram.dtype), gram) - correction
        return gram * precision

    def _fields_correction(self, statistics, colour=None):
        """(3, 3, 4, 4) [c, c', i, j] what the shading fields take off the inner products of vector i in
        channel c and vector j in channel c': under covariance sigma^2 I + B T B' the precision is
        (I - B (G + sigma^2 T^-1)^-1 B') / sigma^2, so x'Qy is the white x'y / sigma^2 less
        (B'x)' (G + sigma^2 T^-1)^-1 (B'y) / sigma^2 (:mod:`mitsuba_p3.fit.fields`). Zero for c != c' when
        every field is a single channel's. ``statistics``: the vectors' field statistics on the pose's
        regions (:meth:`_gram_statistics`; the materials move none of them). Tinted fields load on the
        object's ``colour`` (3,) (:mod:`mitsuba_p3.fit.fields`)."""
        import jax.numpy as jnp

        from ..fit.fields import column_statistics, per_region

        # (the fields' scales and loadings do not depend on the window; the basis came with the statistics)
        variances, _, loading = fields_form(self.config, 1, 1, colours=colour, xp=jnp)
        _, gram, _, _ = column_statistics(statistics, loading, xp=jnp)                       # (R, K, K)
        loading = per_region(jnp.asarray(loading, gram.dtype), gram.shape[0], jnp)
        # B'x for vector i taken in channel c alone: (4, 3, R, K)
        columns = jnp.einsum("rjmc,irmc->icrj", loading, statistics[2])
        size = gram.shape[-1]
        inner = gram + (self.config.sigma ** 2 / jnp.asarray(variances, gram.dtype))[..., None] * jnp.eye(size)
        solved = small_linalg.solve(small_linalg.cholesky(inner, jnp), columns, jnp)        # (4, 3, R, K)
        return jnp.einsum("icrk,jdrk->cdij", columns, solved)

    def _image_from_bases(self, bases, z):
        """The image at position z whose pose, class and shininess gave ``bases`` (H, W, 4, 3)."""
        import jax.numpy as jnp

        p = self.params(z)
        A, D, S, F = (bases[..., i, :] for i in range(4))
        return jnp.clip(p["colour"] * (p["ambient"] * A + p["diffuse"] * D) + p["specular"] * S + F, 0.0, 1.0)

    def _colour_move(self, key, state, bases, gram, observation, target, statistics=None):
        """The colour's conditional given the weights: a 3-D Gaussian mixture (one per GMM component).
        ``statistics``: the bases' :meth:`_gram_statistics` (the tinted fields' way back takes the Gram at the
        proposal's colour from them; computed here if not given). Returns (state, accepted, the Gram matrices
        of the colour kept)."""
        import jax
        import jax.numpy as jnp

        position = state.position
        gmm = self.prior.gmms["colour"]
        cols = slice(SLICES["colour"].start, SLICES["colour"].stop)
        p = self.params(position)
        # per channel, I = c * slope + offset with slope = k_a A + k_d D and offset = k_s S + F
        slope = jnp.stack([p["ambient"], p["diffuse"], 0.0 * p["specular"]])
        offset = jnp.stack([0.0, 0.0, p["specular"]])
        if gram.ndim == 4:
            return self._coupled_colour_move(key, state, bases, gram, observation, target, slope, offset, statistics)
        precision = jnp.einsum("i,cij,j->c", slope, gram[:, :3, :3], slope)       # sum slope^2 / sigma^2
        linear = slope @ gram[:, :3, 3].T - jnp.einsum("i,cij,j->c", slope, gram[:, :3, :3], offset)
        means, variances = jnp.asarray(gmm.means), jnp.asarray(gmm.variances)       # (K, 3)
        post_precision = 1.0 / variances + precision
        post_mean = (means / variances + linear) / post_precision
        log_evidence = jnp.sum(-0.5 * jnp.log1p(variances * precision)
                               + (variances * linear ** 2 + 2 * means * linear - precision * means ** 2)
                               / (2 * (1 + variances * precision)), axis=1)
        log_weights = jax.nn.log_softmax(jnp.log(jnp.asarray(gmm.weights)) + log_evidence)

        def log_q(c):
            per = -0.5 * (jnp.sum(post_precision * (c - post_mean) ** 2, axis=1)
                          - jnp.sum(jnp.log(post_precision / (2 * jnp.pi)), axis=1))
            return jax.scipy.special.logsumexp(log_weights + per)

        k_component, k_noise, k_accept = jax.random.split(key, 3)
        component = jax.random.categorical(k_component, log_weights)
        proposal = post_mean[component] + jax.random.normal(k_noise, (3,)) / jnp.sqrt(post_precision[component])
        current = jnp.asarray(gmm.mean) + jnp.asarray(gmm.std) * position[cols]
        new_position = position.at[cols].set((proposal - gmm.mean) / gmm.std)
        return (*self._independence_mh(k_accept, state, new_position, bases, log_q(current) - log_q(proposal),
                                       observation, target), gram)

    def _coupled_colour_move(self, key, state, bases, gram, observation, target, slope, offset, statistics=None):
        """:meth:`_colour_move` where the noise couples the channels (``gram`` (3, 3, 4, 4)): each GMM
        component's conditional is then a full trivariate Gaussian (:meth:`_coupled_colour_conditional`)."""
        import jax
        import jax.numpy as jnp

        position = state.position
        gmm = self.prior.gmms["colour"]
        cols = slice(SLICES["colour"].start, SLICES["colour"].stop)
        conditional = self._coupled_colour_conditional(gram, slope, offset)
        k_draw, k_accept = jax.random.split(key)
        proposal = conditional.draw(k_draw)
        current = jnp.asarray(gmm.mean) + jnp.asarray(gmm.std) * position[cols]
        new_position = position.at[cols].set((proposal - gmm.mean) / gmm.std)
        if not self._tinted:
            return (*self._independence_mh(k_accept, state, new_position, bases, conditional.log_q(current)
                                           - conditional.log_q(proposal), observation, target), gram)
        # the conditional was built on the current colour's loading: the way back on the proposal's
        statistics = statistics or self._gram_statistics(bases, target[3], observation, position)
        new_gram = self._gram(statistics, target[0], self.params(new_position)["colour"])
        reverse = self._coupled_colour_conditional(new_gram, slope, offset)
        state, accepted = self._independence_mh(k_accept, state, new_position, bases,
                                                reverse.log_q(current) - conditional.log_q(proposal), observation, target)
        return state, accepted, jnp.where(accepted, new_gram, gram)

    def _coupled_colour_conditional(self, gram, slope, offset):
        """The colour's conditional given the weights under coupled channels (``gram`` (3, 3, 4, 4)), the
        render I = c * slope + offset per channel: a :class:`MixtureConditional`, one full trivariate
        Gaussian per GMM component. Exact where the colour stays in [0, 1] (the renderer clips it; the MH
        test corrects the rest)."""
        import jax.numpy as jnp

        gmm = self.prior.gmms["colour"]
        quadratic = jnp.einsum("i,cdij,j->cd", slope, gram[:, :, :3, :3], slope)                # (3, 3)
        linear = (jnp.einsum("i,cdi->c", slope, gram[:, :, :3, 3])
                  - jnp.einsum("i,cdij,j->c", slope, gram[:, :, :3, :3], offset))
        return MixtureConditional.of(jnp.log(jnp.asarray(gmm.weights)), jnp.asarray(gmm.means),
                                     jnp.asarray(gmm.variances), quadratic + 1e-9 * jnp.eye(3), linear)

    def _weight_coordinates(self):
        """The weights (k_a, k_d, k_s): their coordinates in z and the affine map's loc and std (3,)."""
        import jax.numpy as jnp

        gmms = [self.prior.gmms[n] for n in ("ambient", "diffuse", "specular")]
        return (jnp.array([SLICES[n].start for n in ("ambient", "diffuse", "specular")]),
                jnp.array([g.mean[0] for g in gmms]), jnp.array([g.std[0] for g in gmms]))

    def _weights_conditional(self, gram, colour) -> "MixtureConditional":
        """The weights' conditional given the colour and the bases whose ``gram`` is given: a mixture of
        8 trivariate Gaussians (their priors are independent 2-component GMMs)."""
        import itertools

        import jax.numpy as jnp

        gmms = [self.prior.gmms[n] for n in ("ambient", "diffuse", "specular")]
        # every combination of one component per weight: weights (C,), means and variances (C, 3)
        combos = list(itertools.product(*[range(len(g.weights)) for g in gmms]))
        log_w = jnp.array([sum(np.log(g.weights[i]) for g, i in zip(gmms, c)) for c in combos])
        mu = jnp.array([[g.means[i, 0] for g, i in zip(gmms, c)] for c in combos])
        var = jnp.array([[g.variances[i, 0] for g, i in zip(gmms, c)] for c in combos])
        # per channel the image is w . (k_a A, k_d D, k_s S) + F with w = (c, c, 1)
        w = jnp.stack([colour, colour, jnp.ones(3)], axis=-1)                      # (3 channels, 3)
        if gram.ndim == 4:          # channels coupled by the noise: [c, c', i, j]
            lam = jnp.einsum("ci,cdij,dj->ij", w, gram[:, :, :3, :3], w) + 1e-9 * jnp.eye(3)
            eta = jnp.einsum("ci,cdi->i", w, gram[:, :, :3, 3])
        else:
            lam = jnp.einsum("ci,cij,cj->ij", w, gram[:, :3, :3], w) + 1e-9 * jnp.eye(3)
            eta = jnp.einsum("ci,ci->i", w, gram[:, :3, 3])
        return MixtureConditional.of(log_w, mu, var, lam, eta)

    def _weights_move(self, key, state, bases, gram, observation, target):
        """The weights' conditional given the colour (:meth:`_weights_conditional`): an independence
        proposal drawn from it, accepted with the exact log joint."""
        import jax

        k_draw, k_accept = jax.random.split(key)
        position = state.position
        dims, loc, std = self._weight_coordinates()
        conditional = self._weights_conditional(gram, self.params(position)["colour"])
        proposal = conditional.draw(k_draw)
        current = loc + std * position[dims]
        new_position = position.at[dims].set((proposal - loc) / std)
        return self._independence_mh(k_accept, state, new_position, bases,
                                     conditional.log_q(current) - conditional.log_q(proposal), observation, target)

    def _independence_mh(self, key, state, new_position, bases, log_q_ratio, observation, target):
        """Accept or reject an independence proposal with the exact (tempered) log joint, the image
        computed from the bases; ``target`` is (tempering, log prior, the window's term of the pose and the
        pixels its object covers, which a material move keeps)."""
        import jax
        import jax.numpy as jnp

        tempering, log_prior, term, objects = target
        image = self._image_from_bases(bases, new_position)
        new_loglikelihood = self._score(image, objects, observation, new_position) + term
        new_logdensity = log_prior(new_position) + tempering * new_loglikelihood
        accept = jnp.log(jax.random.uniform(key)) < new_logdensity - state.logdensity + log_q_ratio
        kept = (jnp.where(accept, new_position, state.position), jnp.where(accept, new_logdensity, state.logdensity))
        if isinstance(state, ScoredState):     # the log likelihood of the state kept, as the move computed it
            kept = kept + (jnp.where(accept, new_loglikelihood, state.loglikelihood),)
        return type(state)(*kept), accept
