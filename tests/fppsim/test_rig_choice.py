"""The one rig resolver (``fppsim.dataio.rig_choice.resolve_rig``) and the one image-against-camera check
(``fppsim.geometry.rig.check_image_size``): precedence flag > checkpoint > dataset > per-sample > default, each
with the reason the commands print."""

import json

import pytest

from fppsim.errors import RigError
from fppsim.geometry.rig import Rig, check_image_size, make_parallel_rig
from fppsim.dataio.rig_choice import DEFAULT_REASON, PER_SAMPLE_REASON, dataset_rig, resolve_rig


def _dataset(folder, rig=None, jitter=None, meta_rig=None):
    folder.mkdir(parents=True)
    settings = {"config": {"rig_jitter": jitter}} if jitter is not None else {"config": {}}
    if rig is not None:
        settings["rig"] = rig.to_dict()
    (folder / "dataset.json").write_text(json.dumps(settings))
    if meta_rig is not None:
        (folder / "000000").mkdir()
        (folder / "000000" / "meta.json").write_text(json.dumps({"rig": meta_rig.to_dict()}))
    return folder


def test_precedence_and_reasons(tmp_path):
    parallel = make_parallel_rig()
    parallel.name = "mine"
    parallel.save(tmp_path / "my.json")
    ds = _dataset(tmp_path / "ds", rig=parallel)
    own = parallel.to_dict()
    rig, why = resolve_rig(tmp_path / "my.json", checkpoint_rig=own, datasets=[ds])
    assert rig.name == "mine" and why == str(tmp_path / "my.json")
    assert resolve_rig(parallel, name="x.json")[1] == "x.json"
    assert resolve_rig(parallel)[1] == "the given rig"
    assert resolve_rig(None, checkpoint_rig=own, datasets=[ds])[1] == "the checkpoint's rig"
    rig, why = resolve_rig(None, datasets=[tmp_path / "nothing-here", ds])
    assert rig.name == "mine" and why == f"the dataset's rig ({ds}/dataset.json)"
    assert resolve_rig(None, per_sample=True) == (None, PER_SAMPLE_REASON)
    rig, why = resolve_rig(None)
    assert why == DEFAULT_REASON and rig.to_dict() == Rig.default().to_dict()


def test_dataset_rig_from_a_sample_and_jitter_refused(tmp_path):
    parallel = make_parallel_rig()
    ds = _dataset(tmp_path / "ds", meta_rig=parallel)
    rig, why = dataset_rig(ds)
    assert rig.to_dict() == parallel.to_dict() and "meta.json" in why
    assert dataset_rig(_dataset(tmp_path / "empty")) == (None, "")
    with pytest.raises(RigError, match="rig-jitter"):
        dataset_rig(_dataset(tmp_path / "jit", rig=parallel, jitter={"yaw": 0.01}))


def test_unusable_checkpoint_rig_named(tmp_path):
    doc = make_parallel_rig().to_dict()
    doc["projector"] = doc["camera"]  # zero baseline: fringes never move
    with pytest.raises(RigError, match="run/best.pt: its rig"):
        resolve_rig(None, checkpoint_rig=doc, checkpoint="run/best.pt")


def test_check_image_size():
    rig = make_parallel_rig()  # 640 x 352
    check_image_size(rig, (352, 640), "a.png")
    check_image_size(rig.to_dict(), (352, 640), "a.png")
    check_image_size(rig.camera, (352, 640), "a.png")
    with pytest.raises(RigError, match=r"^a.png: image is 64x32 but the rig's camera is 640x352$"):
        check_image_size(rig, (32, 64), "a.png")
    with pytest.raises(ValueError, match=r"^rig camera is 640 x 352 but images are 64 x 32 \(b\); hint$"):
        check_image_size(rig, (32, 64), "b", who="rig camera is", hint="; hint", error=ValueError, sep=" x ",
                         template="{who} {camera} but images are {got} ({what}){hint}")
    with pytest.raises(RigError, match=r"\(3, 32, 64\)"):
        check_image_size(rig, (3, 32, 64), "c")
