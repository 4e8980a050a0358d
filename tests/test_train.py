"""Training end to end with the tiny preset: artifact, determinism, exact resume, what is optimized."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from igavatar.artifacts.manifest import read_artifact
from igavatar.training import body_prior
from igavatar.training.checkpoint import flatten, load_state, save_state
from igavatar.training.config import preset
from igavatar.training.trainer import Trainer
from igavatar_cli.main import app
from igavatar.avatar.dataset import read_dataset, training_data
from igavatar.avatar.model import build_avatar
from stages.train import TrainOptions, resolve_config, run_train


def _trainer(dataset: Path, **overrides) -> Trainer:
    artifact = read_dataset(dataset)
    config = dataclasses.replace(preset("tiny"), **overrides)
    torch.manual_seed(config.seed)
    avatar = build_avatar(config, artifact.subject, artifact.data["pose_dim"])
    return Trainer(config, training_data(artifact), avatar)


def test_tiny_training_writes_a_valid_model_artifact(tiny_model):
    manifest = read_artifact(tiny_model, expected="model")
    data = manifest["data"]
    assert data["steps"] == 6 and data["body_model"] == "anny"
    assert data["speed"]["iterations_per_second"] > 0 and data["speed"]["samples_per_second"] > 0
    assert manifest["peak_memory"]["ram_bytes"] > 0 and manifest["config"]["preset"] == "tiny"
    assert np.isfinite(data["final"]["loss"])
    assert len(list((tiny_model / "validation").glob("*.png"))) == 2
    state = flatten(load_state(tiny_model / "weights.npz"))
    # The beta cap is +inf when the preset does not anneal it; everything else must be finite.
    ceiling = [k for k in state if k.endswith("density.beta_ceiling")]
    assert len(ceiling) == 1 and np.isposinf(state.pop(ceiling[0]))
    tensors = [v for v in state.values() if v.dtype.kind == "f"]
    assert tensors and all(np.isfinite(v).all() for v in tensors)
    assert not tiny_model.with_name("model.work").exists(), "checkpoint directory left behind"


def test_training_is_deterministic_with_a_seed(small_run):
    runs = []
    for _ in range(2):
        trainer = _trainer(small_run / "dataset", steps=3)
        logs = [trainer.train_step() for _ in range(3)]
        runs.append((logs, trainer.avatar.state_dict()))
    assert [l["loss"] for l in runs[0][0]] == [l["loss"] for l in runs[1][0]]
    first, second = flatten(runs[0][1]), flatten(runs[1][1])
    assert first.keys() == second.keys()
    for key, value in first.items():
        assert np.array_equal(value, second[key]), key


def test_a_checkpoint_keeps_empty_dicts_and_lists(tmp_path):
    """An optimizer that has not stepped has an empty "state" (load_state_dict needs the key), and a
    run's list of pose passes starts empty: both come back as they went in."""
    optimizer = torch.optim.Adam([torch.nn.Parameter(torch.zeros(3))], lr=0.1)
    state = {"optimizer": optimizer.state_dict(), "passes": [], "done": [{"step": 3, "kept": 2.5}], "none": None}
    save_state(tmp_path / "state.npz", state)
    loaded = load_state(tmp_path / "state.npz")
    assert loaded["optimizer"]["state"] == {} and loaded["passes"] == []  # (tuples come back as lists)
    assert loaded["done"] == [{"step": 3, "kept": 2.5}] and loaded["none"] is None
    optimizer.load_state_dict(loaded["optimizer"])


@pytest.mark.parametrize("overrides", [{}, {"error_sampling": 1.0}], ids=["uniform", "error-map"])
def test_resume_continues_exactly(small_run, tmp_path, overrides):
    straight = _trainer(small_run / "dataset", steps=4, **overrides)
    for _ in range(4):
        straight.train_step()

    first = _trainer(small_run / "dataset", steps=4, **overrides)
    for _ in range(2):
        first.train_step()
    save_state(tmp_path / "ckpt.npz", {"trainer": first.state_dict()})
    resumed = _trainer(small_run / "dataset", steps=4, **overrides)
    resumed.load_state_dict(load_state(tmp_path / "ckpt.npz")["trainer"])
    for _ in range(2):
        resumed.train_step()
    expected, got = flatten(straight.avatar.state_dict()), flatten(resumed.avatar.state_dict())
    for key, value in expected.items():
        assert np.array_equal(got[key], value), key
    if straight.error_map is not None:  # the map is part of the state: the same draws after resuming
        assert torch.equal(straight.error_map.cells, resumed.error_map.cells)


def test_every_learned_part_is_optimized_including_non_rigid(small_run):
    trainer = _trainer(small_run / "dataset", steps=4, nonrigid_start_fraction=0.0)
    optimized = {id(p) for group in trainer.param_groups() for p in group["params"]}
    names = {n for n, p in trainer.avatar.named_parameters() if id(p) not in optimized}
    assert not names, f"parameters missing from the optimizer: {names}"
    before = {n: p.detach().clone() for n, p in trainer.avatar.named_parameters() if n.startswith("nonrigid.")}
    for _ in range(3):
        trainer.train_step()
    assert trainer.avatar.nonrigid.enabled
    changed = [n for n, p in trainer.avatar.named_parameters() if n in before and not torch.equal(p, before[n])]
    assert changed, "non-rigid parameters did not change"


@pytest.mark.parametrize("regularizer", ["none", "fd-eikonal", "curvature", "fd-eikonal+curvature", "hybrid-pe"])
def test_ablation_regularizers_train(small_run, regularizer):
    from igavatar.training.config import with_overrides

    config = with_overrides(dataclasses.replace(preset("tiny"), steps=8), regularizer=regularizer)
    dataset = read_dataset(small_run / "dataset")
    torch.manual_seed(0)
    avatar = build_avatar(config, dataset.subject, dataset.data["pose_dim"])
    trainer = Trainer(config, training_data(dataset), avatar)
    logs = [trainer.train_step() for _ in range(2)]
    expected = {"none": {"eikonal"}, "fd-eikonal": {"fd_eikonal"}, "curvature": {"eikonal", "curvature"},
                "fd-eikonal+curvature": {"fd_eikonal", "curvature"}, "hybrid-pe": {"eikonal"}}[regularizer]
    assert expected <= set(logs[-1]) and "smooth" not in logs[-1]
    assert all(np.isfinite(l["loss"]) for l in logs)
    if regularizer == "hybrid-pe":
        assert trainer.avatar.config.sdf.pe_frequencies == config.hybrid_pe_frequencies > 0
        assert trainer.avatar.sdf_field.level_weights[-1] < 1, "fine levels should still be closed"


@pytest.mark.parametrize("pairs", ["valid", "adjacent", "monotone", "screen"])
def test_smooth_pair_variants_train(small_run, pairs):
    """Each L_smooth pairing runs a step with a finite, positive smooth term; screen pairs use the
    uncompacted layout (one slot per bin on every ray of the patches)."""
    trainer = _trainer(small_run / "dataset", steps=8, smooth_pairs=pairs)
    logs = [trainer.train_step() for _ in range(3)]
    assert all(np.isfinite(l["loss"]) for l in logs)
    assert any(l["smooth"] > 0 for l in logs)


def test_unknown_smooth_pairs_is_a_clear_error(small_run, cli_runner, tmp_path):
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "m"),
                                     "--preset", "tiny", "--smooth-pairs", "diagonal"])
    assert result.exit_code == 2 and "--smooth-pairs" in result.output and "adjacent" in result.output


def test_cli_train_resume_without_checkpoint_is_a_clear_error(small_run, cli_runner, tmp_path):
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "m"),
                                     "--preset", "tiny", "--resume"])
    assert result.exit_code == 2 and "no checkpoint" in result.output


def test_cli_train_on_a_capture_is_the_wrong_artifact_kind(small_run, cli_runner, tmp_path):
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "capture"), "--out", str(tmp_path / "m"),
                                     "--preset", "tiny"])
    assert result.exit_code == 3 and "needs a dataset artifact" in result.output
    assert not (tmp_path / "m").exists()


def test_unknown_preset_and_regularizer(small_run, cli_runner, tmp_path):
    for args, message in ((["--preset", "huge"], "unknown"), (["--regularizer", "magic"], "expected one of")):
        result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "m"), *args])
        assert result.exit_code == 2 and message in result.output


def test_loaded_model_poses_like_the_dataset_and_mesh_vertices_map_back(small_run, tiny_model):
    """load_model rebuilds the avatar; its pose() reproduces the dataset's transforms; posing a
    canonical mesh vertex and canonicalising it again gives the vertex back."""
    from igavatar.body.anny_body import AnnyBody
    from igavatar.capture.capture_v1 import read_capture_v1
    from igavatar.avatar.model import load_model

    model = load_model(tiny_model)
    weights = load_state(tiny_model / "weights.npz")["avatar"]
    assert torch.equal(model.avatar.sdf_field.encoding.table, weights["sdf_field.encoding.table"])

    capture = read_capture_v1(small_run / "capture")
    body = AnnyBody.load(model.manifest["data"]["subject"]["phenotype"])
    rotations, translation = body.local_rotations_from_pose_parameters(torch.tensor(capture.poses["pose_parameters"]))
    posed = model.pose(rotations, translation)
    frames = np.load(small_run / "dataset" / "frames.npz")
    np.testing.assert_allclose(posed.bone_transforms.numpy(), frames["bone_transforms"], atol=1e-4)
    np.testing.assert_allclose(posed.pose_condition.numpy(), frames["pose_condition"], atol=1e-4)

    # Points on the template surface: pose them, then invert with the deformer.
    import trimesh

    x_canonical = np.asarray(trimesh.load(small_run / "dataset" / "template.ply", process=False).vertices)[::50]
    posed_avatar = model.posed(posed.bone_transforms[-1], posed.pose_condition[-1])
    frame = posed_avatar.frame
    x_posed = posed_avatar.pose_vertices(x_canonical)
    candidates, valid = model.avatar.deformer.canonicalize(torch.from_numpy(x_posed), frame)
    with torch.no_grad():  # the rigid root plus the non-rigid offset is the canonical surface point
        offset = model.avatar.offset_points(candidates.reshape(-1, 3), posed.pose_condition[-1]).reshape(candidates.shape)
    error = (offset - torch.from_numpy(x_canonical).float()[:, None]).norm(dim=-1)
    error = torch.where(valid, error, torch.inf).amin(dim=1)
    assert (error < 1e-3).float().mean() > 0.95, float((error < 1e-3).float().mean())


@pytest.mark.parametrize("table_adam", ["sparse", "dense"])
def test_hash_table_adam_sparse_moves_only_reached_entries_dense_also_the_rest(small_run, table_adam):
    trainer = _trainer(small_run / "dataset", steps=4, table_adam=table_adam)
    table = trainer.avatar.sdf_field.encoding.table
    for _ in range(2):
        trainer.train_step()
    before = table.detach().clone()
    trainer.train_step()
    groups = trainer.param_groups()
    assert groups[0]["params"] == [table] and len(groups) == 3
    assert groups[0]["lr"] == pytest.approx(trainer.config.lr * trainer.learning_rate_factor(2))
    moved, reached = table.detach() != before, table.grad != 0   # the grad of the last step
    assert bool(reached.any()) and not bool(reached.all())
    if table_adam == "sparse":
        assert torch.equal(moved, reached), "SparseAdam moves exactly the entries this step reached"
        assert bool((trainer.table_optimizer.state[table]["steps"] == 0).any())
    else:
        assert trainer.table_optimizer is None
        assert bool((moved & ~reached).any()), "torch's Adam moves entries reached only on earlier steps"


def test_sdf_encoding_override_and_beta_cap_schedule(small_run):
    from igavatar.errors import InputError
    from igavatar.training.config import MLP_SDF, preset, with_overrides

    mlp = with_overrides(preset("tiny"), sdf_encoding="mlp")
    assert mlp.avatar.sdf.use_hash_grid is False and mlp.avatar.sdf.pe_frequencies == MLP_SDF["pe_frequencies"]
    assert with_overrides(preset("tiny")).avatar.sdf.use_hash_grid is True
    with pytest.raises(InputError, match="--sdf-encoding"):
        with_overrides(preset("tiny"), sdf_encoding="siren")
    with pytest.raises(InputError, match="--table-adam"):
        with_overrides(preset("tiny"), table_adam="lazy")
    with pytest.raises(InputError, match="--table-lr-factor"):
        with_overrides(preset("tiny"), table_lr_factor=0.0)
    assert preset("cpu").table_lr_factor == 2.0 and preset("paper").table_lr_factor == 1.0
    assert preset("cpu").table_adam == preset("paper").table_adam == "sparse"
    cpu = preset("cpu")
    assert cpu.beta_final is not None and preset("paper").beta_final is None

    # The cap anneals geometrically from beta_init to beta_final by the anneal fraction, then holds.
    trainer = _trainer(small_run / "dataset", steps=10, beta_final=0.004, beta_anneal_fraction=0.5)
    start = trainer.config.avatar.density.beta_init
    assert trainer.beta_ceiling(0) == pytest.approx(start)
    assert trainer.beta_ceiling(5) == pytest.approx(0.004) and trainer.beta_ceiling(9) == pytest.approx(0.004)
    assert trainer.beta_ceiling(2) == pytest.approx(start * (0.004 / start) ** 0.4)
    logs = [trainer.train_step() for _ in range(6)]
    assert logs[-1]["beta"] <= 0.004 + 1e-9


def test_mlp_only_sdf_trains_without_a_hash_table(small_run):
    from igavatar.training.config import with_overrides

    config = with_overrides(dataclasses.replace(preset("tiny"), steps=4), sdf_encoding="mlp")
    dataset = read_dataset(small_run / "dataset")
    torch.manual_seed(0)
    avatar = build_avatar(config, dataset.subject, dataset.data["pose_dim"])
    trainer = Trainer(config, training_data(dataset), avatar)
    assert trainer.param_groups()[0]["params"] == []  # the hash-table group is empty
    before = [p.detach().clone() for p in trainer.avatar.sdf_field.parameters()]
    logs = [trainer.train_step() for _ in range(2)]
    assert all(np.isfinite(l["loss"]) for l in logs)
    assert any(not torch.equal(a, b) for a, b in zip(before, trainer.avatar.sdf_field.parameters()))


def test_a_step_without_valid_samples_is_counted_not_stepped(small_run):
    trainer = _trainer(small_run / "dataset", steps=4)
    before = {n: p.detach().clone() for n, p in trainer.avatar.named_parameters()}
    trainer.canonical_grid.occupied.zero_()  # empty space everywhere: no valid sample on any ray
    trainer._update_occupancy = lambda: None  # keep the grid empty
    logs = trainer.train_step()
    assert trainer.step == 1 and logs["samples"] == 0 and np.isfinite(logs["loss"])
    assert all(torch.equal(p, before[n]) for n, p in trainer.avatar.named_parameters())


def test_shape_init_artifact_holds_the_initial_fit_and_a_rerun_matches_a_fresh_run(small_run, tmp_path):
    """The saved shape initialization is the fit before training, so a second run into the same
    --out (which reuses it as a cache) starts where a fresh run starts and ends where it ends."""
    from stages.train import TrainOptions, run_train

    options = dict(dataset=small_run / "dataset", preset="tiny", steps=2, device="cpu")
    run_train(TrainOptions(out=tmp_path / "reused", **options))
    init = load_state(tmp_path / "reused" / "shape_init.npz")["sdf"]
    trained = load_state(tmp_path / "reused" / "weights.npz")["avatar"]
    assert init.keys() and all(f"sdf_field.{name}" in trained for name in init)
    assert not np.array_equal(init["encoding.table"], trained["sdf_field.encoding.table"]), "shape_init.npz holds the trained SDF"

    # The same options again: skipped, the model untouched; --force trains, reusing reused/shape_init.npz.
    before = (tmp_path / "reused" / "weights.npz").read_bytes()
    summary = run_train(TrainOptions(out=tmp_path / "reused", **options))
    assert summary["skipped"].startswith("inputs and options unchanged")
    assert (tmp_path / "reused" / "weights.npz").read_bytes() == before
    run_train(TrainOptions(out=tmp_path / "reused", force=True, **options))
    run_train(TrainOptions(out=tmp_path / "fresh", **options))
    again = flatten(load_state(tmp_path / "reused" / "weights.npz")["avatar"])
    fresh = flatten(load_state(tmp_path / "fresh" / "weights.npz")["avatar"])
    assert again.keys() == fresh.keys()
    for key, value in fresh.items():
        assert np.array_equal(again[key], value), key


def test_free_space_term_trains_and_new_options_are_checked(small_run, cli_runner, tmp_path):
    config = preset("tiny")
    config = dataclasses.replace(config, steps=3, loss_weights=dataclasses.replace(config.loss_weights, free_space=1.0),
                                 hull_in_occupancy=True)
    dataset = read_dataset(small_run / "dataset")
    trainer = Trainer(config, training_data(dataset), build_avatar(config, dataset.subject, dataset.data["pose_dim"]))
    assert trainer.hull is not None and 0.0 < trainer.hull.occupied_fraction < 1.0
    logs = [trainer.train_step() for _ in range(3)]
    assert all("free_space" in log and np.isfinite(log["free_space"]) for log in logs)
    # Cells inside the hull stay occupied whatever the density says (growth beyond the prior).
    assert bool((trainer.canonical_grid.occupied | ~trainer._hull_cells()).all())

    resolved = resolve_config(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "m", preset="tiny", beta_init=0.02,
                                           beta_final=0.001, free_space_weight=0.5, smooth_form="released",
                                           beta_anneal_fraction=0.5, lr_decay_power=1.0))
    assert resolved.avatar.density.beta_init == 0.02 and resolved.beta_final == 0.001
    assert resolved.beta_anneal_fraction == 0.5 and resolved.lr_decay_power == 1.0
    assert resolved.loss_weights.free_space == 0.5 and resolved.smooth_form == "released"
    for flags in (["--beta-final", "0.5"], ["--smooth-form", "squared"], ["--free-space-weight", "-1"], ["--smooth-band", "0"],
                  ["--beta-anneal-fraction", "0"], ["--lr-decay-power", "-1"]):
        result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "bad"),
                                         "--preset", "tiny", *flags])
        assert result.exit_code != 0 and flags[0] in result.output and "Traceback" not in result.output


def test_body_inside_term_reads_the_template_and_is_checked(small_run, cli_runner, tmp_path, monkeypatch):
    from stages.train import _body_template

    dataset = read_dataset(small_run / "dataset")
    template = _body_template(dataset)
    assert template is not None and template[0].shape[1] == 3
    config = dataclasses.replace(preset("tiny"), steps=3, loss_weights=dataclasses.replace(preset("tiny").loss_weights, body_inside=10.0))
    trainer = Trainer(config, training_data(dataset), build_avatar(config, dataset.subject, dataset.data["pose_dim"]),
                      body_template=template)
    body = trainer.body_inside
    assert body is not None and 0 < len(body.points) <= body.sampled and (body.template_sdf < 0).all()
    check = trainer.body_inside_check
    # 64 px masks: a pixel is ~3 cm at the subject, too coarse to tell a centimetre of excess.
    assert check["used"] and check["kept"] == len(body.points) and 0 <= check["spill"] <= 1
    assert check["pixel_m"] > body_prior.SPILL_CHECK_MAX_PIXEL_M and not check["spill_checked"]
    # The same template grown by 5 cm (a fit far too heavy), with the check made at any pixel size:
    # its spill past the masks turns the term off (the check itself: tests/test_body_prior.py).
    monkeypatch.setattr(body_prior, "SPILL_CHECK_MAX_PIXEL_M", 1.0)
    mesh = trimesh.Trimesh(*template, process=False)
    heavy = (mesh.vertices + 0.05 * mesh.vertex_normals, mesh.faces)
    refused = Trainer(config, training_data(dataset), build_avatar(config, dataset.subject, dataset.data["pose_dim"]),
                      body_template=heavy)
    assert refused.body_inside is None and "body_inside" not in refused.train_step()
    assert refused.body_inside_check["spill_checked"] and not refused.body_inside_check["used"]
    assert refused.body_inside_check["spill"] > max(check["max_spill"], check["spill"])
    # --body-inside-max-spill 1: the user trusts the fit (tight masks, say): the term stays.
    trusting = dataclasses.replace(config, body_inside_max_spill=1.0)
    kept = Trainer(trusting, training_data(dataset), build_avatar(trusting, dataset.subject, dataset.data["pose_dim"]),
                   body_template=heavy)
    assert kept.body_inside is not None and kept.body_inside_check["used"] and "body_inside" in kept.train_step()
    logs = [trainer.train_step() for _ in range(3)]
    assert all("body_inside" in log and np.isfinite(log["body_inside"]) and log["body_inside"] >= 0 for log in logs)
    # Weight 0 (or no template) builds nothing and adds no term.
    off = Trainer(preset("tiny"), training_data(dataset), build_avatar(preset("tiny"), dataset.subject, dataset.data["pose_dim"]),
                  body_template=template)
    assert off.body_inside is None and "body_inside" not in off.train_step()
    assert preset("cpu").loss_weights.body_inside > 0 and preset("paper").loss_weights.body_inside == 0
    # L_smooth at the paper's weight 1 in both presets (smooth-band-weight.md); --smooth-weight overrides it.
    assert preset("cpu").loss_weights.smooth == 1.0 and preset("paper").loss_weights.smooth == 1.0
    assert resolve_config(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "m", preset="cpu",
                                       smooth_weight=0.5)).loss_weights.smooth == 0.5
    resolved = resolve_config(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "m", preset="tiny", body_inside_weight=2.0))
    assert resolved.loss_weights.body_inside == 2.0
    # The model manifest records the check (validated against schemas/model.schema.json on write).
    monkeypatch.undo()
    run_train(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "m", preset="tiny", steps=2,
                           body_inside_weight=2.0, device="cpu"))
    recorded = read_artifact(tmp_path / "m", expected="model")["data"]["body_inside"]
    assert recorded["used"] and recorded["kept"] == check["kept"] and recorded["spill"] == pytest.approx(check["spill"])
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "bad"),
                                     "--preset", "tiny", "--body-inside-weight", "-1"])
    assert result.exit_code != 0 and "--body-inside-weight" in result.output and "Traceback" not in result.output
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "bad"),
                                     "--preset", "tiny", "--body-inside-max-spill", "1.5"])
    assert result.exit_code != 0 and "--body-inside-max-spill" in result.output and "Traceback" not in result.output
    assert resolve_config(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "m", preset="tiny",
                                       body_inside_max_spill=1.0)).body_inside_max_spill == 1.0
