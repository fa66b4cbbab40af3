"""Atomic writes: the whole file or nothing, with the usual file mode."""
from __future__ import annotations

import os

import pytest

from mitsuba_p3.files import atomic_json, atomic_path, atomic_write


def test_atomic_write_replaces_whole_files_with_the_usual_mode(tmp_path):
    target = atomic_write(tmp_path / "sub" / "a.txt", "first")
    atomic_json(target, {"second": 2})
    assert target.read_text().strip().startswith("{") and "second" in target.read_text()
    mask = os.umask(0)
    os.umask(mask)
    assert os.stat(target).st_mode & 0o777 == 0o666 & ~mask


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = atomic_write(tmp_path / "a.txt", "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as temporary:
            temporary.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


@pytest.mark.parametrize("content, refused", [
    ({}, None),                                          # new or empty: fine
    ({"run.json": "{}"}, None),                          # its own output: resumed
    ({"labels.json": "{}", "scene.xml": "<scene/>"}, "data set"),
    ({"model.json": "{}"}, "fitted model"),
    ({"notes.txt": "mine"}, "not empty"),
])
def test_an_output_folder_is_new_empty_or_the_commands_own(tmp_path, content, refused):
    """Nothing is written into a data set, a model or a folder of someone else's files (one line, no traceback)."""
    from mitsuba_p3.errors import MitsubaP3Error
    from mitsuba_p3.files import claim_output_folder

    folder = tmp_path / "out"
    if content:
        folder.mkdir()
        for name, text in content.items():
            (folder / name).write_text(text)
    before = {p.name: p.read_text() for p in folder.iterdir()} if folder.exists() else {}
    if refused is None:
        assert claim_output_folder(folder, "run.json", "mitsuba-p3 evaluate").is_dir()
    else:
        with pytest.raises(MitsubaP3Error, match=refused):
            claim_output_folder(folder, "run.json", "mitsuba-p3 evaluate")
        assert {p.name: p.read_text() for p in folder.iterdir()} == before
    (tmp_path / "file").write_text("x")
    with pytest.raises(MitsubaP3Error, match="is a file"):
        claim_output_folder(tmp_path / "file", "run.json", "mitsuba-p3 evaluate")


def test_images_are_read_as_colours_whatever_their_encoding(tmp_path):
    """Palette PNGs and GIFs give their colours (not palette indices); CMYK JPEGs their RGB."""
    import numpy as np
    from PIL import Image

    from mitsuba_p3.images import read_png

    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[:, :4] = (200, 30, 40)
    rgb[:, 4:] = (10, 120, 250)
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=4).save(tmp_path / "p.png")
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=4).save(tmp_path / "p.gif")
    Image.fromarray(rgb).convert("CMYK").save(tmp_path / "c.jpg", quality=100)
    for name, tolerance in (("p.png", 1e-6), ("p.gif", 1e-6), ("c.jpg", 0.03)):
        np.testing.assert_allclose(read_png(tmp_path / name), rgb / 255.0, atol=tolerance, err_msg=name)


@pytest.mark.parametrize("name, refused", [("out.jpg", None), ("out.png", None), ("out.exr", "cannot write .exr"),
                                           ("newdir/", "is a folder"), ("afile/x.png", "is a file")])
def test_image_outputs_are_written_as_named_or_refused(tmp_path, name, refused):
    import numpy as np
    from PIL import Image

    from mitsuba_p3.errors import ImageError
    from mitsuba_p3.images import write_image

    (tmp_path / "afile").write_text("x")
    target = f"{tmp_path}/{name}"
    image = np.full((4, 6, 3), 0.5, np.float32)
    if refused:
        with pytest.raises(ImageError, match=refused):
            write_image(target, image)
        return
    write_image(target, image)
    with Image.open(target) as written:
        assert written.format == {"out.jpg": "JPEG", "out.png": "PNG"}[name] and written.size == (6, 4)


@pytest.fixture
def protected(tmp_path):
    """A data set (labels.json) and a fitted model (model.json) side by side."""
    (tmp_path / "data" / "train" / "red").mkdir(parents=True)
    (tmp_path / "data" / "labels.json").write_text("{}")
    (tmp_path / "data" / "train" / "red" / "0.png").write_bytes(b"labelled")
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "model.json").write_text("{}")
    return tmp_path


@pytest.mark.parametrize("target", ["data/train/red/0.png", "data/train/red/new.png", "data/sheet.png",
                                    "model/figure.png"])
def test_no_image_is_written_inside_a_data_set_or_model(protected, target):
    from mitsuba_p3.errors import MitsubaP3Error
    from mitsuba_p3.images import check_image_output

    with pytest.raises(MitsubaP3Error, match="lies inside a (benchmark data set|fitted model)"):
        check_image_output(protected / target)
    assert (protected / "data" / "train" / "red" / "0.png").read_bytes() == b"labelled"
    check_image_output(protected / "elsewhere" / "sheet.png")          # outside both: fine


def test_no_output_folder_inside_a_data_set_or_model_even_through_a_link(protected):
    from mitsuba_p3.errors import MitsubaP3Error
    from mitsuba_p3.files import claim_output_folder, refuse_protected_folder

    (protected / "link").symlink_to(protected / "data")
    for inside in ("data/train/mymodel", "model/run", "link/run"):
        with pytest.raises(MitsubaP3Error, match="lies inside"):
            claim_output_folder(protected / inside, "model.json", "mitsuba-p3 fit")
        assert not (protected / inside).exists() or inside.startswith("link")
    with pytest.raises(MitsubaP3Error, match="is a benchmark data set"):
        refuse_protected_folder(protected / "data", "mitsuba-p3 reproduce")
    with pytest.raises(MitsubaP3Error, match="lies inside a fitted model"):
        refuse_protected_folder(protected / "model" / "tables", "mitsuba-p3 reproduce")
    refuse_protected_folder(protected / "results", "mitsuba-p3 reproduce")


def test_commands_refuse_to_write_into_a_data_set(protected):
    from mitsuba_p3.baselines.train import TrainConfig, meta_train
    from mitsuba_p3.benchmarks.generate import generate
    from mitsuba_p3.errors import MitsubaP3Error
    from mitsuba_p3.reproduce import reproduce

    with pytest.raises(MitsubaP3Error, match="lies inside a benchmark data set"):
        meta_train({}, protected / "data" / "baseline", TrainConfig())
    with pytest.raises(MitsubaP3Error, match="is a benchmark data set"):
        reproduce(protected, protected / "data")
    with pytest.raises(MitsubaP3Error, match="lies inside a fitted model"):
        generate("fsclvr", protected / "model" / "bench", size="small")
    with pytest.raises(MitsubaP3Error, match="is a fitted model"):
        generate("fsclvr", protected / "model", size="small")
    assert sorted(p.name for p in (protected / "model").iterdir()) == ["model.json"]


def test_a_readers_lock_waits_for_no_writer(tmp_path):
    """infer holds a model folder shared while fit holds it exclusively: each refuses the other;
    readers share."""
    import subprocess
    import sys

    from mitsuba_p3.errors import MitsubaP3Error
    from mitsuba_p3.files import folder_lock

    def holder(shared):
        process = subprocess.Popen([sys.executable, "-c", "import time; from mitsuba_p3.files import folder_lock\n"
                                    f"with folder_lock({str(tmp_path)!r}, 'test', shared={shared}):\n"
                                    "    print('held', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
        assert process.stdout.readline().strip() == "held"
        return process

    writer = holder(False)
    with pytest.raises(MitsubaP3Error, match="being written by another run"):
        with folder_lock(tmp_path, "mitsuba-p3 infer", shared=True):
            pass
    writer.kill()
    writer.wait()
    reader = holder(True)
    with folder_lock(tmp_path, "mitsuba-p3 infer", shared=True):   # readers share
        pass
    with pytest.raises(MitsubaP3Error, match="in use by another run"):
        with folder_lock(tmp_path, "mitsuba-p3 fit"):
            pass
    reader.kill()
    reader.wait()
