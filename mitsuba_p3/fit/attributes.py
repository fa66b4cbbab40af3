"""What a posterior says about the object's attributes: shape, material kind, size and colour.

A posterior is a cloud of scene parameters; a person asks "is it a large red
metal sphere?". :class:`AttributeRules` turns posterior samples into those words:

- **shape**: the most frequent shape class among the draws (and its frequency);
- **material kind** (rubber or metal): a logistic regression on the Phong
  weights (k_a, k_d, k_s, log alpha), learnt from the materials the fit
  optimised on the *train* classes, whose kinds the labels give; applied to the
  posterior medians. An evaluation, which holds train posteriors, learns it from
  those instead (:meth:`AttributeRules.with_material_from_posteriors`), with the
  saturation of the median reflectance as a fifth feature and the log of the posterior's
  *Phong misfit* (:mod:`mitsuba_p3.infer.misfit`: how much of the object the best Phong
  render at its pose leaves unexplained) as a sixth. Each kind's examples weigh half the total, so the
  rule's prior on a kind is the protocol's half, not its share of the train classes (:data:`KIND_WEIGHTS`).
  The learnt rule is plain numbers
  (:class:`MaterialModel`): ``evaluate`` saves it in its run folder and ``infer
  --material-rule`` applies it to a new image;
- **size** (small or large): the protocol size nearest, in log space, to the
  median of the posterior's half-extents;
- **colour**: the colour name of the fitted train material whose *chromaticity*
  (reflectance c (k_a + k_d) divided by its sum) is nearest to that of the
  posterior median reflectance. The product, not c alone: the image fixes c k_a
  and c k_d, while c and the weights trade off along a ridge. Chromaticity, not
  the reflectance itself: its brightness trades off against the specular weight
  and the light (a metal's fitted reflectance is half a rubber's of the same
  colour), while its hue names the colour; and each material on its own, not a
  colour's mean over rubber and metal, which lies between the two. A colour
  never seen in training falls back to its label RGB. An evaluation moves each
  centre to the mean chromaticity of its colour and kind's train posteriors
  (:meth:`AttributeRules.with_colours_from_posteriors`), as it learns the
  material rule from them.

A model folder can carry rules learnt the same way from cheaper inputs, the material's
conditional posterior at the *true* poses of a few train images per class
(:mod:`mitsuba_p3.infer.truth_rules`, ``mitsuba-p3 fit``'s last stage, :data:`LEARNT_RULES_FILE`);
:func:`rules_for` reads them in place of the fit's materials' while the fit is the one they
were learnt for, so a lone ``infer`` reads a posterior against posterior-like inputs too.

Every rule is fitted on train classes or fixed by the protocol; nothing is tuned
on test images.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..scene import COLOURS, SIZES
from ..shapes import SHAPES

KINDS = ("rubber", "metal")
# How the material rule weighs its training examples by kind: "balanced", each kind's examples weighed to half
# of the total, a prior of one half on each kind (half of the 96 primitive classes are of each, and a benchmark's
# train and test classes are drawn from them alike); None, as they come, the prior then the kind's share of the
# train classes. The two are level on held-out train classes; balanced is chosen for the prior the protocol fixes.
KIND_WEIGHTS = "balanced"
# a model folder's attribute rules learnt from the material at its train images' true poses
# (mitsuba_p3.infer.truth_rules; rules_for reads them)
LEARNT_RULES_FILE = "attribute-rules.json"


# The material rule's inputs: the Phong weights; the weights and the saturation of the reflectance
# (a white highlight that Phong's lobe does not fully explain pales a metal's fitted colour); and
# those with the log Phong misfit (a metal's mirrored surroundings are what Phong cannot render).
MATERIAL_FEATURES = ("weights", "weights+saturation", "weights+saturation+misfit")


def _material_features(rows, features: str = "weights") -> np.ndarray:
    """(n, 4) features of Phong weights: k_a, k_d, k_s, log alpha; with ``weights+saturation`` (n, 5),
    the reflectance's saturation after them (rows then need ``saturation``); with
    ``weights+saturation+misfit`` (n, 6), the log Phong misfit last (rows then need ``misfit``)."""
    if features not in MATERIAL_FEATURES:
        raise ValueError(f"unknown material features {features!r}; choose {' or '.join(MATERIAL_FEATURES)}")
    rows = list(rows)
    if features.endswith("+misfit") and any(r.get("misfit") is None for r in rows):
        raise ValueError(f"material features {features!r} need each posterior's Phong misfit "
                         "(mitsuba_p3.infer.misfit); none was given")
    return np.array([[r["ambient"], r["diffuse"], r["specular"], np.log(max(r["shininess"], 1e-3))]
                     + ([r["saturation"]] if "saturation" in features else [])
                     + ([np.log(max(r["misfit"], 1e-3))] if features.endswith("+misfit") else [])
                     for r in rows], np.float64)


def saturation(rgb: np.ndarray) -> np.ndarray:
    """HSV saturation (max - min) / max of rgb (..., 3); 0 for black."""
    rgb = np.maximum(np.asarray(rgb, np.float64), 0.0)
    top = rgb.max(axis=-1)
    return np.where(top > 1e-9, (top - rgb.min(axis=-1)) / np.maximum(top, 1e-9), 0.0)


def reflectance(material) -> np.ndarray:
    """c (k_a + k_d): the colour the image identifies, (3,) for a material or (n, 3) for samples.

    Read as the renderer reads a sample (:func:`mitsuba_p3.space.render_params`): the colour clipped to
    [0, 1], the weights to >= 0; a prior draw's negative channel or weight renders as zero, not below it."""
    colour = np.clip(np.asarray(material["colour"], np.float64), 0.0, 1.0).reshape(-1, 3)
    weight = (np.maximum(np.asarray(material["ambient"], np.float64), 0.0)
              + np.maximum(np.asarray(material["diffuse"], np.float64), 0.0)).reshape(-1, 1)
    product = colour * weight
    return product[0] if np.ndim(material["colour"]) == 1 else product


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    """rgb / (r + g + b): the colour without its brightness (black: equal thirds)."""
    rgb = np.maximum(np.asarray(rgb, np.float64), 0.0)
    total = rgb.sum(axis=-1, keepdims=True)
    return np.where(total > 1e-9, rgb / np.maximum(total, 1e-9), 1.0 / 3.0)



def median_chromaticity(samples: dict) -> np.ndarray:
    """(3,) the chromaticity of the posterior samples' median reflectance: what the colour rule reads."""
    return chromaticity(np.median(reflectance(samples), axis=0))

@dataclass
class AttributeRules:
    """Decision rules from posterior samples to attribute names (see the module docstring)."""

    material_model: MaterialModel | None     # None: one kind only
    only_kind: str | None                    # the kind when training had just one
    colour_names: list[str]                  # per reference: its colour name
    colour_albedos: np.ndarray               # (references, 3) chromaticities of the train materials
    material_features: str = "weights"       # the material model's inputs (MATERIAL_FEATURES)
    colour_kinds: list | None = None         # per reference: its material kind (None: a label RGB's colour)

    @classmethod
    def from_materials(cls, materials: dict[str, dict], extra_colours: dict[str, tuple] | None = None
                       ) -> "AttributeRules":
        """Rules learnt from a fit's ``materials.json`` (keys ``colour-kind``, e.g. ``red-metal``)."""
        keys = list(materials)
        kinds = [key.rsplit("-", 1)[1] for key in keys]
        present = sorted(set(kinds) & set(KINDS))
        model, only = None, (present[0] if len(present) == 1 else None)
        if len(present) == 2:
            model = material_classifier(_material_features(materials[k] for k in keys), kinds)
        names = [key.rsplit("-", 1)[0] for key in keys]
        centres = [chromaticity(reflectance(materials[key])) for key in keys]
        reference_kinds: list = list(kinds)
        for name, rgb in (extra_colours or {}).items():   # colours the fit never saw: their label RGB (0-255)
            if name not in names:
                names.append(name)
                centres.append(chromaticity(np.asarray(rgb, np.float64)))
                reference_kinds.append(None)
        return cls(model, only, names, np.array(centres, np.float64), colour_kinds=reference_kinds)

    def with_colours_from_posteriors(self, samples: list[dict], colours: list[str], kinds: list[str]
                                     ) -> "AttributeRules":
        """The same rules with each fitted material's colour centre moved to the mean chromaticity of
        the median reflectances of the *train* posteriors of its colour and kind (``samples`` with their
        labelled ``colours`` and ``kinds``), as the material rule is learnt from posteriors: the centre
        is then the kind of input it is compared with (a start of the fit can tint its materials). A centre without such posteriors,
        or a label RGB's, is kept."""
        from dataclasses import replace

        if self.colour_kinds is None or not (len(samples) == len(colours) == len(kinds)):
            raise ValueError("colour centres need every posterior's colour and kind, and rules from a fit")
        points: dict[tuple, list] = {}
        for sample, colour, kind in zip(samples, colours, kinds):
            points.setdefault((colour, kind), []).append(median_chromaticity(sample))
        centres = np.array(self.colour_albedos, np.float64)
        for i, key in enumerate(zip(self.colour_names, self.colour_kinds)):
            if key[1] is not None and key in points:
                centres[i] = np.mean(points[key], axis=0)
        return replace(self, colour_albedos=centres)

    def with_material_from_posteriors(self, samples: list[dict], kinds: list[str], features: str = "weights",
                                      misfits: list[float] | None = None) -> "AttributeRules":
        """The same rules with the material kind learnt from posteriors of *train* images (their
        samples and labelled kinds, and with ``...+misfit`` features their Phong misfits) instead
        of the fit's materials: the classifier then sees at training the same kind of input,
        posterior medians, that it is applied to. Unchanged when the train images hold one kind only."""
        from dataclasses import replace

        if len(set(kinds) & set(KINDS)) < 2:
            return self
        misfits = [None] * len(samples) if misfits is None else list(misfits)
        if len(misfits) != len(samples):
            raise ValueError(f"{len(misfits)} misfits for {len(samples)} posteriors")
        rows = [{**_medians(s), "misfit": m} for s, m in zip(samples, misfits)]
        return replace(self, material_features=features,
                       material_model=material_classifier(_material_features(rows, features), kinds))

    def material_record(self) -> dict:
        """The material rule and the colour centres as JSON-ready numbers (:meth:`with_material_record`
        reads them back)."""
        return {"format": "mitsuba-p3-material-rule", "features": self.material_features, "kinds": list(KINDS),
                "kind_weights": KIND_WEIGHTS,
                "only_kind": self.only_kind,
                "model": None if self.material_model is None else asdict(self.material_model),
                "colour_centres": {"names": list(self.colour_names), "kinds": list(self.colour_kinds or []),
                                   "chromaticities": np.asarray(self.colour_albedos).tolist()}}

    def with_material_record(self, record: dict) -> "AttributeRules":
        """The same rules with the material rule of :meth:`material_record` (e.g. one ``evaluate`` learnt
        from its train posteriors and saved as ``material-rule-LIKELIHOOD.json``)."""
        from dataclasses import replace

        if not isinstance(record, dict) or record.get("format") != "mitsuba-p3-material-rule":
            raise ValueError("not a material rule (mitsuba-p3 evaluate writes RUN/material-rule-p3.json)")
        if record.get("kinds") != list(KINDS) or record.get("features") not in MATERIAL_FEATURES:
            raise ValueError(f"a material rule for kinds {record.get('kinds')} on features "
                             f"{record.get('features')!r}; this version reads {list(KINDS)} on {MATERIAL_FEATURES}")
        model = record.get("model")
        rules = replace(self, material_features=record["features"], only_kind=record.get("only_kind"),
                        material_model=None if model is None else MaterialModel(
                            tuple(model["mean"]), tuple(model["scale"]), tuple(model["coef"]), float(model["intercept"])))
        centres = record.get("colour_centres")      # absent in records written before 2026-11-29
        if centres:
            rules = rules._with_centres(centres["names"], centres["kinds"] or [None] * len(centres["names"]),
                                        centres["chromaticities"])
        return rules

    def _with_centres(self, names, kinds, chromaticities) -> "AttributeRules":
        """The same rules with the centre of each (colour name, kind) in the lists replaced (one the
        rules lack added); every other centre (e.g. a colour's label RGB the record never saw) kept."""
        from dataclasses import replace

        own_kinds = list(self.colour_kinds) if self.colour_kinds is not None else [None] * len(self.colour_names)
        keys = list(zip(self.colour_names, own_kinds))
        centres = [np.asarray(c, np.float64) for c in self.colour_albedos]
        for name, kind, chromaticity in zip(names, kinds, chromaticities):
            if (name, kind) in keys:
                centres[keys.index((name, kind))] = np.asarray(chromaticity, np.float64)
            else:
                keys.append((name, kind))
                centres.append(np.asarray(chromaticity, np.float64))
        return replace(self, colour_names=[k[0] for k in keys], colour_kinds=[k[1] for k in keys],
                       colour_albedos=np.array(centres, np.float64))

    @property
    def reads_misfit(self) -> bool:
        """Whether :meth:`decide` needs the posterior's Phong misfit."""
        return self.material_model is not None and self.material_features.endswith("+misfit")

    def colour_name(self, colour: np.ndarray) -> str:
        """The colour name of the reference chromaticity nearest ``colour`` (3,), a chromaticity."""
        return self.colour_names[int(np.argmin(np.sum((self.colour_albedos - colour) ** 2, axis=1)))]

    def decide(self, samples: dict, misfit: float | None = None) -> dict:
        """Attribute names (and the shape's posterior probabilities) from posterior samples:
        ``class`` (n,), ``scale`` (n, 3), ``colour`` (n, 3), ``ambient``/``diffuse``/``specular``/``shininess``
        (n, 1); ``misfit``, the posterior's Phong misfit, when the material rule reads it."""
        counts = np.bincount(np.asarray(samples["class"], int).ravel(), minlength=len(SHAPES)).astype(float)
        shape_probabilities = counts / counts.sum()
        medians = {**_medians(samples), "misfit": misfit}
        if self.material_model is not None:
            metal = float(self.material_model.predict_proba(_material_features([medians], self.material_features))[0, 1])
            kind = KINDS[int(metal > 0.5)]
        else:
            kind, metal = self.only_kind, float(self.only_kind == "metal")
        half_extent = float(np.median(np.asarray(samples["scale"])))
        size = min(SIZES, key=lambda s: abs(np.log(half_extent / SIZES[s])))
        nearest = self.colour_name(median_chromaticity(samples))
        return {"shape": SHAPES[int(np.argmax(counts))], "shape_probabilities": shape_probabilities.tolist(),
                "material": kind, "p_metal": metal, "size": size, "half_extent_m": half_extent, "colour": nearest}


def _medians(samples: dict) -> dict:
    """Posterior medians of the Phong weights, and the saturation of the median reflectance."""
    medians = {k: float(np.median(samples[k])) for k in ("ambient", "diffuse", "specular", "shininess")}
    medians["saturation"] = float(saturation(np.median(reflectance(samples), axis=0)))
    return medians


@dataclass(frozen=True)
class MaterialModel:
    """A fitted logistic regression on standardised features: p(metal) = sigmoid(w . (x - mean) / scale + b).
    Plain numbers, so a rule learnt in one command (``evaluate``) can be saved and read by another
    (``infer --material-rule``)."""

    mean: tuple
    scale: tuple
    coef: tuple
    intercept: float

    def predict_proba(self, features: np.ndarray) -> np.ndarray:
        """(n, 2) probabilities of rubber and metal, as sklearn's classifiers give them."""
        z = (np.asarray(features, np.float64) - np.asarray(self.mean)) / np.asarray(self.scale)
        metal = 1.0 / (1.0 + np.exp(-(z @ np.asarray(self.coef) + self.intercept)))
        return np.stack([1.0 - metal, metal], axis=1)


def material_classifier(features: np.ndarray, kinds: list[str]) -> MaterialModel:
    """Logistic regression (standardised features, sklearn's L2 penalty C = 1) from Phong-weight
    features to metal vs rubber, the two kinds weighed as :data:`KIND_WEIGHTS` says."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import StandardScaler

    scaler = StandardScaler().fit(features)
    fitted = LogisticRegression(C=1.0, class_weight=KIND_WEIGHTS).fit(
        scaler.transform(features), np.array([KINDS.index(k) for k in kinds]))
    return MaterialModel(tuple(scaler.mean_.tolist()), tuple(scaler.scale_.tolist()),
                         tuple(fitted.coef_[0].tolist()), float(fitted.intercept_[0]))


def rules_for(fitted, dataset=None, learnt: bool = True) -> AttributeRules:
    """The rules of a fitted model; a data set's colours the fit never saw join with their label RGB.

    With ``learnt`` (the default) and a model folder that carries rules learnt at the train images'
    true poses (:data:`LEARNT_RULES_FILE`, written by ``mitsuba-p3 fit``: :mod:`mitsuba_p3.infer.truth_rules`)
    for the fit as it is now, its material rule and colour centres replace those made from the fit's
    materials; ``learnt=False`` gives the fit's own."""
    extra = dict(COLOURS)
    if dataset is not None:
        labels = dataset.class_labels
        extra.update({labels[name].colour: tuple(rgb) for name, rgb in dataset.rgb.items() if rgb})
    rules = AttributeRules.from_materials(fitted.materials, extra)
    record = learnt_rules_record(fitted) if learnt else None
    return rules.with_material_record(record) if record else rules


def learnt_rules_record(fitted) -> dict | None:
    """The model folder's learnt attribute rules (:data:`LEARNT_RULES_FILE`) when they were learnt for the
    fit as it is (its model.json's digest); None when there are none or the fit changed since (a warning)."""
    import json
    import warnings

    from ..files import file_digest

    path = fitted.root / LEARNT_RULES_FILE
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    if record.get("model_digest") != file_digest(fitted.root / "model.json"):
        warnings.warn(f"{path} was learnt for an earlier fit of this folder, so the fit's own rules name the "
                      f"attributes; learn them again with mitsuba-p3 fit DATASET --out {fitted.root} --stages rules",
                      stacklevel=2)
        return None
    return record
