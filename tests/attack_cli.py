"""Attacks on the command line, as a hostile but realistic user makes them.

Every attack runs the real ``mitsuba-p3`` command in a scratch folder and is classed by
what the user sees:

- ``refused``: a non-zero exit with a message of at most two lines and no traceback
  (what a mistake must give);
- ``ok``: exit 0 where the command is meant to work, and the attack's own check of the
  result passes (a file really written in the asked format, a data set left intact);
- ``TRACEBACK``, ``SILENT`` (exit 0 where a refusal was due), ``WRONG`` (exit 0 with a
  wrong result), ``LOST`` (a user's file changed or gone), ``VERBOSE`` (a refusal of
  more than two lines), ``SLOW`` (a refusal that came only after ``--slow`` seconds:
  it should be made before any work).

The attacks follow the classes of problem of the issue "Your own data, and nothing
lost": silent wrong results, data lost, late crashes, tracebacks instead of one line,
runaway resources and bringing one's own data set. They need a benchmark folder and a
model fitted to it, and copy what they damage:

    python tests/attack_cli.py --dataset data/fsclvr-lo --model data/models/fsclvr-lo [--only NAME,...]

Prints one line per attack, then JSON: the count per class. The exit status is 1 if any
attack ended in a class other than ``refused`` or ``ok``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

# a sampler small enough that an attack which gets through to sampling ends in seconds
TINY = ["--sampler", "mh", "--chains", "2", "--steps", "4", "--burn-in", "2", "--tune-rounds", "1",
        "--tune-steps", "4"]
CLEAN = ("refused", "ok")


@dataclass
class Attack:
    name: str
    argv: Callable[[Path], list[str]]            # the command line after ``mitsuba-p3``, given the scratch folder
    expect: str = "refuse"                        # refuse or ok
    check: Callable[[Path], str | None] | None = None   # after the run: a problem, or None
    setup: Callable[[Path], object] | None = None       # before the run: make the files the attack needs
    guarded: tuple = ()                           # files (relative to the scratch folder) that must survive unchanged
    tags: list = field(default_factory=list)


def digest(path: Path) -> str:
    """A file's or a folder's contents; a folder's ``.lock`` (the advisory lock a command takes, holding
    its pid: not the user's data, and ignored as such by the commands themselves) does not count."""
    if path.is_dir():
        return hashlib.sha256("".join(digest(p) for p in sorted(path.rglob("*"))
                                      if p.is_file() and p.name != ".lock").encode()).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else "missing"


def tiny_dataset(source: Path, out: Path, test_classes: int = 5, per_class: int = 2, reverse: bool = False) -> Path:
    """A copy of a benchmark cut to a few classes: enough for every few-shot setting of 5 classes and
    1 support, and sampled in seconds (``reverse``: the last classes instead of the first)."""
    labels = json.loads((source / "labels.json").read_text())
    kept, counts = [], {}
    for image in labels["images"][::-1] if reverse else labels["images"]:
        key = (image["split"], json.dumps(image["class"], sort_keys=True))
        limit = test_classes if image["split"] == "test" else 3
        classes = {k for k in counts if k[0] == image["split"]}
        if key not in counts and len(classes) >= limit:
            continue
        if counts.get(key, 0) >= per_class:
            continue
        counts[key] = counts.get(key, 0) + 1
        kept.append(image)
        (out / image["file"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(source / image["file"], out / image["file"])
    if (source / labels.get("scene", "scene.xml")).is_file():
        shutil.copy(source / labels.get("scene", "scene.xml"), out / labels.get("scene", "scene.xml"))
    (out / "labels.json").write_text(json.dumps({**labels, "images": kept}, indent=1))
    return out


def edited_labels(work: Path, name: str, edit: Callable[[dict], None]) -> Path:
    """A copy of the tiny data set whose labels.json ``edit`` changed."""
    folder = work / name
    if not folder.exists():
        shutil.copytree(work / "data", folder)
        labels = json.loads((folder / "labels.json").read_text())
        edit(labels)
        (folder / "labels.json").write_text(json.dumps(labels, indent=1))
    return folder


def damaged_model(work: Path, name: str, damage: Callable[[Path], None]) -> Path:
    folder = work / name
    if not folder.exists():
        shutil.copytree(work / "model", folder)
        damage(folder)
    return folder


def image_of(work: Path, mode: str, suffix: str) -> Path:
    """A test image of the tiny data set saved in another PIL mode and format."""
    from PIL import Image

    labels = json.loads((work / "data" / "labels.json").read_text())
    source = work / "data" / next(i["file"] for i in labels["images"] if i["split"] == "test")
    path = work / f"image-{mode}{suffix}"
    image = Image.open(source).convert("RGB")
    image = image.convert(mode) if mode != "P" else image.quantize(256)
    image.save(path)
    return path


def same_colours(work: Path, mode: str, suffix: str) -> str | None:
    """The reader sees the colours of a palette, CMYK or GIF image, not its indices."""
    from mitsuba_p3.images import read_png

    labels = json.loads((work / "data" / "labels.json").read_text())
    rgb = read_png(work / "data" / next(i["file"] for i in labels["images"] if i["split"] == "test"))
    other = read_png(work / f"image-{mode}{suffix}")
    error = float(np.abs(other - rgb).mean())
    return None if error < 0.05 else f"read with mean error {error:.3f} against the RGB original"


def make_file(relative: str, text: str = "not what the command wants") -> Callable[[Path], None]:
    def setup(w: Path) -> None:
        (w / relative).parent.mkdir(parents=True, exist_ok=True)
        (w / relative).write_text(text)
    return setup


def make_dir(relative: str) -> Callable[[Path], None]:
    return lambda w: (w / relative).mkdir(parents=True, exist_ok=True)


def written_as(path: str, kind: str) -> Callable[[Path], str | None]:
    magic = {"jpeg": b"\xff\xd8", "png": b"\x89PNG"}[kind]

    def check(work: Path) -> str | None:
        file = work / path
        if not file.is_file():
            return f"{path} is not a file"
        return None if file.read_bytes()[:len(magic)] == magic else f"{path} does not hold {kind} bytes"
    return check


def scene_with(work: Path, text_from: str, text_to: str) -> Path:
    root = Path(__file__).resolve().parents[1]
    path = work / f"scene-{hashlib.sha1(text_to.encode()).hexdigest()[:8]}.xml"
    text = (root / "scenes" / "fsclvr.xml").read_text()
    assert text_from in text, text_from
    path.write_text(text.replace(text_from, text_to))
    return path


BACKGROUND: list[subprocess.Popen] = []      # commands an attack left running; stopped at the end


def second_run(argv: Callable[[Path], list[str]]) -> Callable[[Path], list[str]]:
    """Start ``argv`` in the background, wait until it holds its folder's lock, and give the same
    command again."""
    def start(w: Path) -> list[str]:
        command = argv(w)
        BACKGROUND.append(subprocess.Popen(["mitsuba-p3", *command], stdout=subprocess.DEVNULL,
                                           stderr=subprocess.DEVNULL))
        lock = Path(command[command.index("--out") + 1]) / ".lock"
        for _ in range(600):
            if lock.exists() and BACKGROUND[-1].poll() is None:
                break
            time.sleep(0.1)
        time.sleep(2.0)                              # the lock file exists just before it is locked
        return command
    return start


def attacks() -> list[Attack]:
    root = Path(__file__).resolve().parents[1]
    scene = str(root / "scenes" / "fsclvr.xml")

    def infer(out: str, *extra: str, image: Callable[[Path], str] | None = None) -> Callable[[Path], list[str]]:
        """``infer`` of a test image (or ``image(w)``) with the tiny sampler into ``out``."""
        return lambda w: ["infer", (image or test_image)(w), "--model", str(w / "model"), "-o", str(w / out),
                          *TINY, *extra]

    def evaluate(out: str, *extra: str, data: str = "data", model: str = "model") -> Callable[[Path], list[str]]:
        return lambda w: ["evaluate", str(w / data), "--model", str(w / model), "--out", str(w / out),
                          "--spread-shots", "0", "--episodes", "5", "--jobs", "1", *TINY, *extra]

    def test_image(w: Path) -> str:
        labels = json.loads((w / "data" / "labels.json").read_text())
        return str(w / "data" / next(i["file"] for i in labels["images"] if i["split"] == "test"))

    def first_run(w: Path) -> None:
        """A finished evaluation of the tiny data set (the run others attack)."""
        if not (w / "run" / "results.json").exists():
            subprocess.run(["mitsuba-p3", *evaluate("run")(w)], capture_output=True, check=True)

    out = []
    add = out.append
    # -- 1. silent wrong results ------------------------------------------------------------------------
    add(Attack("evaluate: finished run, another data set", evaluate("run", data="other-data"), setup=first_run))
    add(Attack("evaluate: finished run, another model", evaluate("run", model="other-model"), setup=first_run))
    add(Attack("evaluate: finished run, other sampler settings", evaluate("run", "--tune-steps", "5"),
               setup=first_run))
    for mode, suffix in (("P", ".png"), ("P", ".gif"), ("CMYK", ".jpg"), ("L", ".png"), ("RGBA", ".png")):
        add(Attack(f"infer: a {mode} {suffix[1:].upper()} image", (lambda m, s: lambda w: [
            "infer", str(image_of(w, m, s)), "--model", str(w / "model"), "-o", str(w / f"infer-{m}{s[1:]}"),
            *TINY])(mode, suffix), expect="ok", check=(lambda m, s: lambda w: same_colours(w, m, s))(mode, suffix)))
    add(Attack("render: a dodecahedron in a shape group", lambda w: [
        "render", str(scene_with(w, '<shape type="sphere">', '<shape type="dodecahedron">')), "-o",
        str(w / "dodeca.png")]))
    add(Attack("render: -o out.jpg writes JPEG", lambda w: ["render", scene, "-o", str(w / "out.jpg"),
                                                            "--resolution", "60x80"],
               expect="ok", check=written_as("out.jpg", "jpeg")))
    add(Attack("render: -o out.exr", lambda w: ["render", scene, "-o", str(w / "out.exr"), "--resolution", "60x80"]))
    add(Attack("render: -o newdir/", lambda w: ["render", scene, "-o", str(w / "newdir") + "/",
                                                "--resolution", "60x80"]))
    add(Attack("render: -o under a file", lambda w: ["render", scene, "-o", str(w / "afile" / "x.png")],
               setup=make_file("afile"), guarded=("afile",)))
    add(Attack("infer: --sigma inf", infer("s-inf", "--sigma", "inf")))
    add(Attack("infer: --sigma -1", infer("s-neg", "--sigma", "-1")))
    add(Attack("evaluate: --tune-rounds -1", lambda w: evaluate("r-tune")(w) + ["--tune-rounds", "-1"]))
    add(Attack("fit: --light-falloff -1", lambda w: ["fit", str(w / "data"), "--out", str(w / "m-falloff"),
                                                     "--light-falloff", "-1"]))
    add(Attack("reproduce: --light-falloff -1", lambda w: ["reproduce", "--data", str(w), "--out", str(w / "r-falloff"),
                                                           "--light-falloff", "-1"]))
    add(Attack("evaluate: --likelihoods p3,p3", lambda w: evaluate("r-twice")(w) + ["--likelihoods", "p3,p3"]))
    add(Attack("render: fractional kappa", lambda w: ["render", scene, "-o", str(w / "k.png"), "--set",
                                                      "kappa=0.5"]))
    for where, path in (("an absolute image path", "/etc/hostname"), ("an image path out of the folder",
                                                                        "../outside.png")):
        add(Attack(f"benchmark check: {where}", (lambda p, n: lambda w: [
            "benchmark", "check", str(edited_labels(w, f"labels-{n}", lambda l: l["images"][0].update(file=p)))])(
            path, where.split()[1])))
    # -- 2. data lost ---------------------------------------------------------------------------------------
    add(Attack("fit: --out the data set itself", lambda w: ["fit", str(w / "data"), "--out", str(w / "data")],
               guarded=("data",)))
    add(Attack("fit: --out the model of another fit", lambda w: ["fit", str(w / "data"), "--out", str(w / "model")],
               guarded=("model",)))
    add(Attack("evaluate: --out the data set", lambda w: evaluate("data")(w), guarded=("data",)))
    add(Attack("infer: -o the model folder", infer("model"), guarded=("model",)))
    add(Attack("evaluate: -o a folder of the user's files", evaluate("mine"), setup=make_file("mine/notes.txt"),
               guarded=("mine",)))
    first_image = lambda w: Path(test_image(w)).relative_to(w)  # noqa: E731
    add(Attack("render: -o over a labelled image", lambda w: ["render", scene, "-o", test_image(w),
                                                              "--resolution", "60x80"], guarded=("data",)))
    add(Attack("benchmark show: -o inside the data set", lambda w: ["benchmark", "show", str(w / "data"), "-o",
                                                                    str(w / "data" / "sheet.png")], guarded=("data",)))
    add(Attack("fit: --out inside the data set", lambda w: ["fit", str(w / "data"), "--out",
                                                            str(w / "data" / "train" / "mymodel")], guarded=("data",)))
    add(Attack("baseline train: --out the data set", lambda w: ["baseline", "train", "protonets", str(w / "data"),
                                                                "--out", str(w / "data"), "--iterations", "1"],
               guarded=("data",)))
    add(Attack("reproduce: --out the data set", lambda w: ["reproduce", "--data", str(w), "--out", str(w / "data")],
               guarded=("data",)))
    add(Attack("infer: -o inside the model", infer("model/posterior"), guarded=("model",)))

    def replaced_image(w: Path) -> None:
        """A finished run, then its first test image replaced in place by an all-black one."""
        from PIL import Image

        first_run(w)
        run = w / "run-replaced"
        if not run.exists():
            shutil.copytree(w / "data", w / "data-replaced")
            shutil.copytree(w / "run", run)
            record = json.loads((run / "run.json").read_text())
            record["dataset"] = str((w / "data-replaced").resolve())
            (run / "run.json").write_text(json.dumps(record))
            image = w / "data-replaced" / first_image(w).relative_to("data")
            Image.new("RGB", Image.open(image).size).save(image)

    def sampled_again(w: Path) -> str | None:
        stale = list((w / "run-replaced" / "posteriors").rglob("*.stale"))
        return None if stale else "the replaced image was scored with its old cached posterior"
    add(Attack("evaluate: a test image replaced in place", evaluate("run-replaced", data="data-replaced"),
               expect="ok", setup=replaced_image, check=sampled_again))

    def empty_floor(w: Path) -> None:
        from mitsuba_p3.fit.model import FittedModel
        from mitsuba_p3.render import make_renderer

        if not (w / "floor.npy").exists():
            renderer = make_renderer(FittedModel(w / "model").scene(), "mitsuba", height=120, width=160, shadows=True)
            np.save(w / "floor.npy", renderer.render_empty())

    def says_nothing_here(w: Path) -> str | None:
        warnings = json.loads((w / "i-floor" / "estimate.json").read_text()).get("warnings", [])
        return None if any("no object" in x for x in warnings) else "an empty floor answered as an object, no warning"
    add(Attack("infer: an empty floor", lambda w: ["infer", str(w / "floor.npy"), "--model", str(w / "model"), "-o",
                                                  str(w / "i-floor"), "--sampler", "smc", "--particles", "8"],
               expect="ok", setup=empty_floor, check=says_nothing_here))
    add(Attack("infer: --particles 1000000000", infer("i-particles", "--sampler", "smc", "--particles", "1000000000"),
               tags=["fast"]))
    # -- 3. late crashes --------------------------------------------------------------------------------------
    for flag, value in (("--chains", "0"), ("--chains", "-2"), ("--steps", "0"), ("--jobs", "0"), ("--seed", "-1"),
                        ("--burn-in", "-3"), ("--episodes", "0")):
        add(Attack(f"evaluate: {flag} {value}", (lambda f, v: lambda w: evaluate(f"late{f}{v}")(w) + [f, v])(
            flag, value), tags=["fast"]))
    add(Attack("evaluate: an unknown shape", evaluate("r-torus", data="labels-torus"), tags=["fast"],
               setup=lambda w: edited_labels(w, "labels-torus",
                                             lambda l: l["images"][0]["class"].update(shape="torus"))))
    add(Attack("evaluate: a test class with one image", evaluate("r-one", data="labels-one"), tags=["fast"],
               setup=lambda w: edited_labels(w, "labels-one", lambda l: l["images"].remove(
                   next(i for i in l["images"] if i["split"] == "test")))))
    add(Attack("fit: an unknown colour without rgb", lambda w: ["fit", str(edited_labels(
        w, "labels-magenta", lambda l: [i["class"].update(colour="magenta") or i["class"].pop("rgb", None)
                                        for i in l["images"][:1]])), "--out", str(w / "fit-magenta")],
               tags=["fast"]))
    add(Attack("evaluate: a failed start, then the corrected command", evaluate("r-retry", "--episodes", "2"),
               expect="ok", setup=lambda w: subprocess.run(
                   ["mitsuba-p3", *evaluate("r-retry")(w), "--dask", "tcp://127.0.0.1:1"], capture_output=True)))
    # -- 4. tracebacks instead of one line --------------------------------------------------------------------
    damages = {"no priors.json": lambda m: (m / "priors.json").unlink(),
               "truncated priors.json": lambda m: (m / "priors.json").write_text((m / "priors.json").read_text()[:50]),
               "empty model.json": lambda m: (m / "model.json").write_text(""),
               "no scene.npz": lambda m: (m / "scene.npz").unlink(),
               "no features.json": lambda m: (m / "features.json").unlink()}
    for label, damage in damages.items():
        name = "model-" + label.replace(" ", "-").replace(".", "-")
        add(Attack(f"infer: a model with {label}", (lambda n, d: lambda w: [
            "infer", test_image(w), "--model", str(damaged_model(w, n, d)), "-o", str(w / f"i-{n}"), *TINY])(
            name, damage), tags=["fast"]))

    def cut_posterior(size: int) -> Callable[[Path], None]:
        """A copy of the finished run whose first cached posterior is cut to ``size`` bytes."""
        def setup(w: Path) -> None:
            first_run(w)
            run = w / f"cut{size}"
            if not run.exists():
                shutil.copytree(w / "run", run)
                victim = sorted((run / "posteriors" / "p3").glob("*.npz"))[0]
                victim.write_bytes(victim.read_bytes()[:size])
        return setup
    add(Attack("evaluate: a zero-byte cached posterior", evaluate("cut0"), expect="ok", setup=cut_posterior(0)))
    add(Attack("evaluate: a truncated cached posterior", evaluate("cut300"), expect="ok", setup=cut_posterior(300)))
    add(Attack("render: -o an existing directory", lambda w: ["render", scene, "-o", str(w / "adir")],
               setup=make_dir("adir")))
    add(Attack("benchmark show: -o a directory", lambda w: ["benchmark", "show", str(w / "data"), "-o", str(w / "bdir")],
               setup=make_dir("bdir")))
    add(Attack("infer: -o an existing file", infer("taken.txt"), setup=make_file("taken.txt"), guarded=("taken.txt",),
               tags=["fast"]))
    add(Attack("evaluate: --dask at a port nobody listens on", lambda w: evaluate("r-dask")(w)
               + ["--dask", "tcp://127.0.0.1:1"], tags=["fast"]))
    add(Attack("infer: a 240x320 image, short chains", infer("i-big", image=lambda w: str(w / "big.npy")), expect="ok",
               setup=lambda w: np.save(w / "big.npy", np.random.default_rng(0).uniform(size=(240, 320, 3)).astype(np.float32))))
    add(Attack("infer: a missing image", lambda w: ["infer", str(w / "nothing.png"), "--model", str(w / "model"),
                                                   "-o", str(w / "i-missing")]))
    add(Attack("infer: a text file as image", infer("i-text", image=lambda w: str(w / "text.png")),
               setup=make_file("text.png")))
    # -- 5. runaway resources -----------------------------------------------------------------------------------
    add(Attack("render: --resolution 20000x20000", lambda w: ["render", scene, "-o", str(w / "huge.png"),
                                                              "--resolution", "20000x20000"], tags=["fast"]))
    add(Attack("render: --resolution 0x10", lambda w: ["render", scene, "-o", str(w / "zero.png"),
                                                       "--resolution", "0x10"]))
    add(Attack("evaluate: a second run into a folder in use", second_run(evaluate("r-lock", "--spread-shots", "2"))))
    # -- 6. one's own data set ------------------------------------------------------------------------------------
    add(Attack("benchmark check: no scene.xml", lambda w: ["benchmark", "check", str(edited_labels(
        w, "labels-noscene", lambda l: l.pop("scene", None)))], expect="ok"))
    add(Attack("benchmark check: a mesh shape without its mesh", lambda w: ["benchmark", "check", str(edited_labels(
        w, "labels-mesh", lambda l: next(i for i in l["images"] if i["split"] == "test")["class"].update(
            shape="bunny")))]))
    add(Attack("benchmark check: labels.json not JSON", lambda w: ["benchmark", "check", str(w / "badjson")],
               setup=make_file("badjson/labels.json", "{")))
    add(Attack("benchmark check: an empty folder", lambda w: ["benchmark", "check", str(w / "empty")],
               setup=make_dir("empty")))
    # -- what check passed and fit or evaluate later failed on (issue "Refuse what would harm", item 4) ----------
    def check(name: str, edit: Callable[[dict], None], setup: Callable[[Path], None] | None = None) -> Attack:
        def argv(w: Path) -> list[str]:
            folder = edited_labels(w, f"labels-{name}", edit)
            if setup:
                setup(folder)
            return ["benchmark", "check", str(folder)]
        return Attack(f"benchmark check: {name}", argv, tags=["check"])

    def first(split: str) -> Callable[[dict], dict]:
        return lambda l: next(i for i in l["images"] if i["split"] == split)

    def rgba(folder: Path) -> None:
        from PIL import Image

        labels = json.loads((folder / "labels.json").read_text())
        image = np.asarray(Image.open(folder / labels["images"][0]["file"]).convert("RGBA")).copy()
        image[..., 3] = 128
        Image.fromarray(image).save(folder / labels["images"][0]["file"])

    def tiff32(folder: Path) -> None:
        from PIL import Image

        Image.fromarray(np.full((120, 160), 18_000_000, np.int32), mode="I").save(folder / "deep.tif")

    def garbage_mesh(folder: Path) -> None:
        (folder / "garbage.obj").write_text("v 0 0 0\nnot a mesh\n")

    add(check("a garbage mesh file", lambda l: l["images"][0].update(mesh="garbage.obj"), garbage_mesh))
    add(check("an image with transparency", lambda l: None, rgba))
    add(check("a 32-bit integer TIFF", lambda l: l["images"][0].update(file="deep.tif"), tiff32))
    add(check("rgb null", lambda l: l["images"][0]["class"].update(rgb=None, colour="mauve")))
    add(check("rgb 5", lambda l: l["images"][0]["class"].update(rgb=5)))
    add(check("one file as two shots", lambda l: l["images"][1].update(file=l["images"][0]["file"])))
    add(check("a test record on a train image", lambda l: first("test")(l).update(file=first("train")(l)["file"])))
    add(check("object_to_world 10x the scale", lambda l: [row.__setitem__(slice(0, 3), [10 * v for v in row[:3]])
                                                         for row in l["images"][0]["pose"]["object_to_world"][:3]]))
    add(check("a negative shot", lambda l: l["images"][0].update(shot=-3)))
    add(check("an object below the floor", lambda l: (l["images"][0]["pose"].update(z=-0.5),
                                                      l["images"][0]["pose"]["object_to_world"][2].__setitem__(3, -0.5))))
    add(check("material glass", lambda l: l["images"][0]["class"].update(material="glass")))
    add(check("size huge", lambda l: l["images"][0]["class"].update(size="huge")))
    add(check("a yaw given as a string", lambda l: l["images"][0]["pose"].update(yaw=str(l["images"][0]["pose"]["yaw"]))))
    return out


def run(attack: Attack, work: Path, slow: float) -> tuple[str, str, float]:
    """(class, the message the user saw, seconds)."""
    try:
        if attack.setup:
            attack.setup(work)
        argv = attack.argv(work)
    except subprocess.CalledProcessError as error:
        return "SETUP", (error.stderr or b"").decode()[-300:], 0.0
    guarded = {g: digest(work / g) for g in attack.guarded}     # after the set-up, which may make them
    start = time.perf_counter()
    result = subprocess.run(["mitsuba-p3", *argv], capture_output=True, text=True, timeout=900)
    seconds = time.perf_counter() - start
    message = [line for line in result.stderr.strip().splitlines() if "WARNING" not in line and line.strip()]
    shown = message[-1] if message else result.stdout.strip().splitlines()[-1:] or [""]
    shown = shown if isinstance(shown, str) else shown[0]
    lost = [g for g, d in guarded.items() if digest(work / g) != d]
    if lost:
        return "LOST", f"changed: {', '.join(lost)}", seconds
    if "Traceback" in result.stderr:
        return "TRACEBACK", message[-1] if message else "", seconds
    if result.returncode == 0:
        if attack.expect == "refuse":
            return "SILENT", shown, seconds
        problem = attack.check(work) if attack.check else None
        return ("WRONG", problem, seconds) if problem else ("ok", shown, seconds)
    if attack.expect == "ok":
        return "REFUSED-OK", shown, seconds
    if len(message) > 2:
        return "VERBOSE", " / ".join(message[-3:]), seconds
    if "fast" in attack.tags and seconds > slow:
        return "SLOW", shown, seconds
    return "refused", shown, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--only", default="", help="comma-separated words; attacks whose name holds one")
    parser.add_argument("--slow", type=float, default=60.0,
                        help="seconds after which a refusal meant to come before any work counts as SLOW")
    args = parser.parse_args()
    from mitsuba_p3.benchmarks.dataset import load_dataset

    load_dataset(args.dataset)                                  # a clear error for a wrong --dataset
    with tempfile.TemporaryDirectory(prefix="attack-") as scratch:
        work = Path(scratch)
        tiny_dataset(Path(args.dataset), work / "data")
        shutil.copytree(args.model, work / "model")
        other = tiny_dataset(Path(args.dataset), work / "other-data", reverse=True)
        shutil.copytree(args.model, work / "other-model")
        (work / "other-model" / "note.txt").write_text("another model")  # another folder, same contents
        assert other.exists()
        counts = {}
        words = [w.strip().lower() for w in args.only.split(",") if w.strip()]
        for attack in attacks():
            if words and not any(w in attack.name.lower() for w in words):
                continue
            kind, message, seconds = run(attack, work, args.slow)
            counts[kind] = counts.get(kind, 0) + 1
            print(f"{kind:10s} {seconds:5.1f} s  {attack.name}: {message[:160]}", flush=True)
        for process in BACKGROUND:
            process.kill()
            process.wait()
    print(json.dumps(counts, indent=1))
    sys.exit(0 if set(counts) <= set(CLEAN) else 1)


if __name__ == "__main__":
    main()
