"""`python -m drgan.import_official official=DIR out=RUN`: a generator trained with the official DiffRenderGAN code
as a drgan run folder, which `python -m drgan.generate ckpt=RUN` uses as it is.

An official experiment folder holds ``<tag>.json`` (its ``mesh_dict`` and ``scene_param_dict``) and ``G_<epoch>.pth``
(a plain state dict of the parameter MLP, weight-normalised). What carries over, and how:

- meshes: every file of the JSON's ``mesh_path`` is one particle (the official folders hold copies); each distinct
  mesh is read with drgan's validated loader and copied to ``RUN/meshes/``, its file frame kept in the material
  (`drgan.scene.official`);
- layouts: the size distribution with its parameters and the placement (`drgan.scene.placements.OfficialPlacement`:
  units, 2-D/3-D, agglomerates, random or Poisson);
- the scene: the official stage and light meshes (copied to ``RUN/scene/``), emissions, camera, ``direct_projective``,
  the Gaussian filter of ``gaussdev``, ``spp`` (`drgan.scene.official.OfficialScene`);
- parameters: per BSDF key -1 = learned (within the JSON's limits) or a fixed value. The official scene writes a
  surface's *fixed* values from the *other* surface's keys (the particles' from ``s_*``, the stage's from ``p_*``,
  a learned key's -1 read as 0); the material holds the values the official scene renders with;
- the network: its weights, weight norm kept (g, v), its output order (stage, particles, noise sigma) and limits.
  drgan divides the network's input by the view width (256): the first layer's g is multiplied by 256 (exact).

Loading never unpickles code (``weights_only=True``); a key of the JSON or of the state dict that drgan does not
know is an error naming it. Writes ``RUN/checkpoints/best.ckpt``, ``RUN/material/<name>.yaml`` (the material, for
``material=<name>`` with ``hydra.searchpath=[file://RUN]``) and ``RUN/official.json`` (what was imported).
"""

from __future__ import annotations

import json
import logging
import math
import re
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from drgan.core import io
from drgan.core.checkpoint_io import refusing_unsafe
from drgan.core.errors import ConfigError, check_keys
from drgan.launch.runtime import stage_main, start
from drgan.scene import particle_meshes as mesh_files

log = logging.getLogger(__name__)

MESH_KEYS = (
    "mesh_path", "mesh_unit", "mesh_scale", "mesh_base_sample_limit", "mesh_position3d", "mesh_max_agglomerates",
    "mesh_size_dist", "lognormal_params", "bimodal_params", "gaussian_params", "particle_placement",
)  # fmt: skip
# The Principled-BSDF keys of the official scene, in the order its network writes the learned ones.
BSDF_NAMES = (
    "base_color", "sheen", "spec_tint", "metallic", "specular", "anisotropic", "spec_trans", "clearcoat_gloss",
    "clearcoat", "flatness", "sheen_tint", "roughness",
)  # fmt: skip
SCENE_KEYS = (
    "n_hidden", "emission1", "emission2", "spp", "gaussdev", "noise_limit_min", "noise_limit_max",
    "stage_bsdf_limit_min", "stage_bsdf_limit_max", "particle_bsdf_limit_min", "particle_bsdf_limit_max",
    *(f"{surface}_{name}" for surface in "ps" for name in BSDF_NAMES),
)  # fmt: skip
SIZE_PARAMS = {
    "lognormal": ("lognormal_params", ("mu", "sigma")),
    "bimodal": ("bimodal_params", ("mean1", "stddev1", "p", "mean2", "stddev2")),
    "gaussian": ("gaussian_params", ("mean", "stddev")),
}
SIZE_GROUPS = {f"drgan.scene.sizes.{cls}Size": group for cls, group in (("Lognormal", "lognormal"), ("Normal", "normal"), ("Bimodal", "bimodal"))}  # fmt: skip
LAYERS = ("fc1", "fc2", "fc3", "fc4", "output_layer.0")
SCENE_FILES = {"stage_mesh": "stage.ply", "ring_light_mesh": "light_source.ply", "top_light_mesh": "light_source2.ply"}
# The paper's cases by official tag: drgan's material names.
PAPER_NAMES = {
    "Mill2021TiO2_paper": ("tio2_him_paper", "TiO2 nanoparticles in HIM (the paper's generator, epoch 11)"),
    "Mill2021SiO2_paper": ("sio2_him_paper", "SiO2 nanoparticles in HIM (the paper's generator, epoch 48)"),
    "Ruehle2021TiO2_paper": ("tio2_sem_paper", "TiO2 nanoparticles in SEM (the paper's generator, epoch 27)"),
    "Ag_paper": ("agnw_sem_paper", "silver nanowires in multi-beam SEM (the paper's generator, epoch 42)"),
}
# Official scene: the view is 2 x 6 x tan(20 deg) = 4.37 units wide at the particles' plane, 256 px.
PX_PER_UNIT = 256 / (2 * 6 * math.tan(math.radians(20)))
# An official scene value below which a fixed BSDF key counts as learned (-1).
LEARNED = 0.0


# --- reading an official experiment ---------------------------------------------------------------------------


def read_settings(path: Path) -> dict:
    """The experiment's JSON, checked: every key known (an unknown one is an error naming it), every needed one there."""
    try:
        settings = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise ConfigError(f"experiment: {path} is not a readable JSON file ({error})") from None
    if not isinstance(settings, dict):
        raise ConfigError(f"experiment: {path}: expected a JSON object with mesh_dict and scene_param_dict")
    check_keys(f"experiment {path.name}", settings, ("mesh_dict", "scene_param_dict"))
    mesh, scene = settings.get("mesh_dict"), settings.get("scene_param_dict")
    if not isinstance(mesh, dict) or not isinstance(scene, dict):
        raise ConfigError(f"experiment {path.name}: expected mesh_dict and scene_param_dict objects")
    check_keys(f"experiment {path.name}: mesh_dict", mesh, MESH_KEYS)
    check_keys(f"experiment {path.name}: scene_param_dict", scene, SCENE_KEYS)
    size = mesh.get("mesh_size_dist")
    if size not in SIZE_PARAMS:
        raise ConfigError(f"experiment {path.name}: mesh_size_dist={size!r}: expected one of {sorted(SIZE_PARAMS)}")
    group, fields = SIZE_PARAMS[size]
    needed = [k for k in MESH_KEYS if k.startswith("mesh_") or k == "particle_placement"]
    missing = [k for k in needed if k not in mesh] + [f"scene_param_dict.{k}" for k in SCENE_KEYS if k not in scene]
    if not isinstance(mesh.get(group), dict):
        missing.append(f"mesh_dict.{group}")
    if missing:
        raise ConfigError(f"experiment {path.name}: missing {missing}")
    check_keys(f"experiment {path.name}: mesh_dict.{group}", mesh[group], fields)
    absent = [f for f in fields if f not in mesh[group]]
    if absent:
        raise ConfigError(f"experiment {path.name}: mesh_dict.{group} lacks {absent}")
    if mesh["particle_placement"] not in ("random", "poisson"):
        raise ConfigError(
            f"experiment {path.name}: particle_placement={mesh['particle_placement']!r}: expected random or poisson"
        )
    return settings


def read_weights(path: Path) -> dict[str, torch.Tensor]:
    """The official generator's state dict (``weights_only=True``: nothing in it runs), its keys checked."""
    with refusing_unsafe("experiment", path):
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as error:  # noqa: BLE001  (a damaged file: say which)
            if isinstance(error, __import__("pickle").UnpicklingError):
                raise
            raise ConfigError(f"experiment: {path} is not a readable PyTorch state dict ({error})") from None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ConfigError(f"experiment: {path}: expected a state dict of tensors (the official G_<epoch>.pth)")
    known = [f"params_model.{layer}.{part}" for layer in LAYERS for part in ("weight_g", "weight_v", "bias")]
    check_keys(f"experiment {path.name}", state, known, "state dict key")
    missing = [k for k in known if k not in state]
    if missing:
        raise ConfigError(f"experiment {path.name}: the state dict lacks {missing}")
    return {k: state[k].detach().to(torch.float32) for k in known}


def find_experiment(folder: Path, epoch: int | None) -> tuple[Path, Path, int]:
    """(JSON, weights, epoch) of an official experiment folder; ``epoch`` picks among several G_<epoch>.pth."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"experiment={folder}: no such folder (an official experiments/<tag> folder)")
    settings = sorted(folder.glob("*.json"))
    if len(settings) != 1:
        raise ConfigError(f"experiment={folder}: expected one <tag>.json, found {[p.name for p in settings]}")
    weights = {int(m[1]): p for p in folder.glob("G_*.pth") if (m := re.fullmatch(r"G_(\d+)\.pth", p.name))}
    if not weights:
        raise ConfigError(f"experiment={folder}: no G_<epoch>.pth")
    if epoch is None:
        if len(weights) > 1:
            raise ConfigError(f"experiment={folder}: several generators (epochs {sorted(weights)}); give epoch=")
        epoch = next(iter(weights))
    if int(epoch) not in weights:
        raise ConfigError(f"epoch={epoch}: experiment {folder} holds epochs {sorted(weights)}")
    return settings[0], weights[int(epoch)], int(epoch)


def mesh_files_of(mesh_path: str, meshes: Path | None, experiment: Path) -> list[Path]:
    """The files of the official ``mesh_path`` folder, one per particle, sorted by name.

    ``meshes``: a folder with ``index.json`` (official folder -> file name -> distinct file in that folder) or an
    official repository checkout (``mesh_path`` relative to it). Default: ``<experiment>/../../meshes`` when it has
    an index, else the checkout two levels above the experiment."""
    root = Path(experiment).resolve().parent.parent
    candidates = [Path(meshes)] if meshes else [root / "meshes", root]
    for base in candidates:
        index = base / "index.json"
        if index.is_file():
            table = json.loads(index.read_text())
            if mesh_path not in table:
                raise ConfigError(f"meshes={base}: index.json has no folder {mesh_path!r} (has {sorted(table)})")
            return [base / table[mesh_path][name] for name in sorted(table[mesh_path])]
        folder = base / mesh_path
        if folder.is_dir():
            files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".ply", ".obj"))
            if files:
                return files
    raise ConfigError(
        f"mesh_path={mesh_path!r}: not found under {[str(c) for c in candidates]}; give meshes= (a folder with "
        "index.json, or the official repository)"
    )


def scene_files_of(scene: Path | None, experiment: Path) -> dict[str, Path]:
    """The official stage and light PLYs: ``scene`` or <experiment>/../../scene or the checkout's utils/rendering."""
    root = Path(experiment).resolve().parent.parent
    for base in [Path(scene)] if scene else [root / "scene", root / "utils" / "rendering"]:
        files = {key: base / name for key, name in SCENE_FILES.items()}
        if all(p.is_file() for p in files.values()):
            for p in files.values():
                mesh_files.read_mesh(p)  # validated like every mesh drgan reads
            return files
    raise ConfigError(f"scene: no folder with {sorted(SCENE_FILES.values())} (give scene=)")


# --- the drgan equivalents --------------------------------------------------------------------------------------


def bsdf_tables(scene: dict) -> tuple[dict, dict]:
    """(particle_bsdf, stage_bsdf) as the official scene renders them: learned keys (-1) within the JSON's limits,
    in the network's order; a fixed key holds the value of the *other* surface's key of that name (the official
    XML fills the particles' BSDF from ``s_*`` and the stage's from ``p_*``), a learned one read as 0. ``flatness``
    is not a parameter of Mitsuba's principled BSDF (it ignores it): it must be fixed and is left out."""
    tables = {}
    for surface, other in (("p", "s"), ("s", "p")):
        limits = "particle" if surface == "p" else "stage"
        low, high = float(scene[f"{limits}_bsdf_limit_min"]), float(scene[f"{limits}_bsdf_limit_max"])
        table = {}
        for name in BSDF_NAMES:
            if scene[f"{surface}_{name}"] < LEARNED:
                if name == "flatness":
                    raise ConfigError(f"scene_param_dict.{surface}_flatness=-1: flatness cannot be learned")
                table[name] = {"min": low, "max": high}
        for name in BSDF_NAMES:
            if name not in table and name != "flatness":
                value = float(scene[f"{other}_{name}"])
                table[name] = {"value": max(value, 0.0)}
        tables[surface] = table
    return tables["p"], tables["s"]


def size_config(mesh: dict) -> dict:
    """The size group: r of each particle (layout units; the official draws, numpy's parametrisations)."""
    kind = mesh["mesh_size_dist"]
    params = mesh[SIZE_PARAMS[kind][0]]
    if kind == "lognormal":
        return {
            "_target_": "drgan.scene.sizes.LognormalSize",
            "median": math.exp(params["mu"]),
            "sigma": params["sigma"],
        }
    tiny = 1e-6  # drgan truncates normals at a positive size; the official draws are never near 0
    if kind == "gaussian":
        return {
            "_target_": "drgan.scene.sizes.NormalSize",
            "mean": params["mean"],
            "std": params["stddev"],
            "min_size": tiny,
        }
    # The official bimodal draws its mode 2 with probability p.
    return {
        "_target_": "drgan.scene.sizes.BimodalSize",
        "mean1": params["mean1"], "std1": params["stddev1"], "mean2": params["mean2"], "std2": params["stddev2"],
        "weight1": 1.0 - params["p"], "min_size": tiny,
    }  # fmt: skip


def placement_config(mesh: dict) -> dict:
    return {
        "_target_": "drgan.scene.placements.OfficialPlacement",
        "algorithm": mesh["particle_placement"],
        "limit": float(mesh["mesh_base_sample_limit"]) / float(mesh["mesh_unit"]),
        "position3d": bool(mesh["mesh_position3d"]),
        "max_agglomerates": int(mesh["mesh_max_agglomerates"]),
    }


def regressor_state(weights: dict[str, torch.Tensor], view_width: float) -> dict[str, torch.Tensor]:
    """The official MLP's weights as `drgan.models.regressor.ParameterRegressor`'s (Linear layers at net.1, 4, 7,
    10, 12; weight norm kept: original0 = g, original1 = v). drgan feeds the network phi / view_width, so the first
    layer's g is multiplied by view_width (a power of two, 256: exact)."""
    state = {}
    for index, layer in zip((1, 4, 7, 10, 12), LAYERS):
        g = weights[f"params_model.{layer}.weight_g"]
        if layer == "fc1":
            g = g * float(view_width)
        prefix = f"net.{index}"
        state[f"{prefix}.parametrizations.weight.original0"] = g
        state[f"{prefix}.parametrizations.weight.original1"] = weights[f"params_model.{layer}.weight_v"]
        state[f"{prefix}.bias"] = weights[f"params_model.{layer}.bias"]
    return state


def output_limits(settings: dict) -> list[tuple[float, float]]:
    """The official network's outputs in order (stage's learned keys, particles', noise sigma): their limits."""
    scene = settings["scene_param_dict"]
    stage = [n for n in BSDF_NAMES if scene[f"s_{n}"] < LEARNED]
    particle = [n for n in BSDF_NAMES if scene[f"p_{n}"] < LEARNED]
    limit = {k: (float(scene[f"{k}_limit_min"]), float(scene[f"{k}_limit_max"])) for k in ("stage_bsdf", "particle_bsdf", "noise")}  # fmt: skip
    return [limit["stage_bsdf"]] * len(stage) + [limit["particle_bsdf"]] * len(particle) + [limit["noise"]]


def model_config(settings: dict, tag: str, name: str | None, run: Path, mesh_dir: Path, frames, scene_files) -> dict:
    """The drgan model config (material, size, placement, renderer, model, seed) of an official experiment."""
    from drgan.launch.configs import compose

    mesh, scene = settings["mesh_dict"], settings["scene_param_dict"]
    default_name, made_for = PAPER_NAMES.get(tag, (re.sub(r"\W+", "_", tag.lower()), f"official experiment {tag}"))
    particle_bsdf, stage_bsdf = bsdf_tables(scene)
    n = len(frames[1])
    extent = float(np.mean([f[3] for f in frames[0]]))
    size = size_config(mesh)
    median_r = size.get("median", size.get("mean", size.get("mean1", 1.0)))
    material = {
        "name": name or default_name,
        "made_for": made_for,
        "polarity": "bright",
        "n_particles": n,
        "n_particles_min": None,
        "view_width": 256,
        # largest extent in px of a particle of median r at the particles' plane (informative; nothing sizes by it)
        "particle_size_px": float(median_r * mesh["mesh_scale"] ** 2 * extent * PX_PER_UNIT),
        "size_spread": float(size.get("sigma", 0.25)),
        "contour_px": 1,  # the official masks' contour is 1 px wide
        "filter_stddev": float(scene["gaussdev"]),
        "noise_sigma": {"min": float(scene["noise_limit_min"]), "max": float(scene["noise_limit_max"])},
        "noise_grain_px": 0.0,
        "background_texture": {"enabled": False, "highpass_px": 8.0},
        "meshes": {"kind": "sphere", "count": len(frames[0]), "seed": 0, "dir": str(mesh_dir), "params": {}},
        "imaging": {
            "_target_": "drgan.scene.official.OfficialScene",
            "mesh_unit": float(mesh["mesh_unit"]),
            "mesh_scale": float(mesh["mesh_scale"]),
            "mesh_frames": [list(map(float, f)) for f in frames[0]],
            **{key: str(path) for key, path in scene_files.items()},
            "ring_radiance": float(scene["emission1"]),
            "top_radiance": float(scene["emission2"]),
            "particle_bsdf": particle_bsdf,
            "stage_bsdf": stage_bsdf,
        },
    }
    base = compose(["material=sio2_him", "renderer=direct_projective"], config_name="render")
    renderer = OmegaConf.to_container(base.renderer, resolve=True)
    renderer.update({"spp": int(scene["spp"]), "grad_spp": None, "resolution": 256})
    model = OmegaConf.to_container(base.model, resolve=True)
    model.update({"hidden": int(scene["n_hidden"]), "dropout": 0.2})  # the official RegressionModel's
    return {
        "material": material,
        "size": size,
        "placement": placement_config(mesh),
        "renderer": renderer,
        "model": model,
        "seed": 0,
    }


def copy_meshes(files: list[Path], mesh_dir: Path) -> tuple[Path, list[list[float]]]:
    """The experiment's meshes copied into ``mesh_dir`` (emptied first), each validated; (the folder, each copied
    mesh's [centre x, y, z, extent]). Each distinct file once: particle k takes mesh k % count, so each must serve as
    many particles (true of the paper's folders); otherwise one file per particle."""
    uses = Counter(p.resolve() for p in files)
    distinct = sorted(uses, key=lambda p: p.name)
    per_particle = len(set(uses.values())) > 1
    if mesh_dir.exists():
        shutil.rmtree(mesh_dir)
    mesh_dir.mkdir(parents=True)
    sources = files if per_particle else distinct
    frames = []
    for k, source in enumerate(sources):
        centre, extent = mesh_files.mesh_frame(source)  # validated: a bad file raises MeshError naming it
        target = mesh_dir / (f"p{k:03d}_{source.name}" if per_particle else source.name)
        shutil.copyfile(source, target)
        frames.append([*centre.tolist(), extent])
    if [p.name for p in sorted(mesh_dir.iterdir())] != [
        (f"p{k:03d}_{s.name}" if per_particle else s.name) for k, s in enumerate(sources)
    ]:
        raise ConfigError(f"meshes: file names of {sources} do not keep their order when sorted")
    return mesh_dir, frames


def copy_scene_files(sources: dict[str, Path], scene_dir: Path) -> dict[str, Path]:
    """The scene's files (key -> path) copied into ``scene_dir``; key -> the copy."""
    scene_dir.mkdir(parents=True, exist_ok=True)
    copied = {}
    for key, source in sources.items():
        shutil.copyfile(source, scene_dir / source.name)
        copied[key] = scene_dir / source.name
    return copied


def import_experiment(
    experiment: Path, out: Path, *, epoch: int | None = None, meshes: Path | None = None, scene: Path | None = None,
    name: str | None = None,
) -> Path:  # fmt: skip
    """Import an official experiment folder into the drgan run folder ``out``; returns its checkpoint."""
    from drgan.models.gan_module import GANModule
    from drgan.scene.config import typed_material

    json_path, weights_path, epoch = find_experiment(Path(experiment), epoch)
    tag = json_path.stem
    settings = read_settings(json_path)
    weights = read_weights(weights_path)
    out = Path(out).expanduser().resolve()
    files = mesh_files_of(settings["mesh_dict"]["mesh_path"], meshes, Path(experiment))
    n = len(files)
    inputs = weights["params_model.fc1.weight_v"].shape[1]
    if inputs != 4 * n:
        raise ConfigError(
            f"experiment {tag}: the network reads {inputs} inputs but {settings['mesh_dict']['mesh_path']} holds {n} "
            f"meshes ({4 * n} inputs): not this experiment's meshes"
        )
    limits = output_limits(settings)
    if weights["params_model.output_layer.0.weight_v"].shape[0] != len(limits):
        raise ConfigError(
            f"experiment {tag}: the network has {weights['params_model.output_layer.0.weight_v'].shape[0]} outputs; "
            f"its JSON learns {len(limits)} values (stage, particles, noise)"
        )

    mesh_dir, frames = copy_meshes(files, out / "meshes")
    scene_files = copy_scene_files(scene_files_of(scene, Path(experiment)), out / "scene")

    cfg = model_config(settings, tag, name, out, mesh_dir, (frames, files), scene_files)
    material = typed_material(cfg["material"])
    module = GANModule.from_config(cfg, base_dir=out)
    learned = [p.key for p in module.generator.learned]
    module.generator.regressor.load_state_dict(regressor_state(weights, material.view_width))
    checkpoint = {
        "state_dict": module.state_dict(),
        "hyper_parameters": {"cfg": cfg, "m": None, "base_dir": str(out)},
        "epoch": epoch,
        "global_step": 0,
        "drgan": {"phi_rng_state": module.phi_rng.get_state(), "skipped_steps": 0},
        "official": {"tag": tag, "epoch": epoch},
    }
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    target = out / "checkpoints" / "best.ckpt"
    torch.save(checkpoint, target)
    io.write_json(
        out / "official.json",
        {
            "tag": tag, "epoch": epoch, "settings": settings, "weights": str(weights_path),
            "outputs": learned, "output_limits": limits,
            "mesh_files": [str(p) for p in files], "meshes": [p.name for p in sorted(mesh_dir.iterdir())],
        },
    )  # fmt: skip
    write_material_file(out, cfg)
    log.info("imported %s (epoch %d) into %s: outputs %s", tag, epoch, out, learned)
    return target


def write_material_file(out: Path, cfg: dict) -> Path:
    """``RUN/material/<name>.yaml``: the imported material as a config file (``material=<name>`` with
    ``hydra.searchpath=[file://RUN]``), with its size, placement and renderer."""
    name = cfg["material"]["name"]
    body = OmegaConf.to_yaml(
        OmegaConf.create(
            {
                "material": cfg["material"],
                "size": cfg["size"],
                "placement": cfg["placement"],
                "renderer": {"integrator": "direct_projective", "spp": cfg["renderer"]["spp"], "grad_spp": None},
                "model": {"hidden": cfg["model"]["hidden"], "dropout": cfg["model"]["dropout"]},
            }
        )
    )
    header = (
        "# @package _global_\n"
        f"# {cfg['material']['made_for']}: written by drgan.import_official (the official experiment's settings).\n"
        "defaults:\n"
        "  - /drgan_schema/material@material\n"
        "  - /drgan_schema/imaging/official@material.imaging\n"
        f"  - override /size: {SIZE_GROUPS[cfg['size']['_target_']]}\n"
        "  - override /placement: official\n\n"
    )
    path = out / "material" / f"{name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(header + body)
    return path


@stage_main("conf/gan", "import_official")
def main(cfg: DictConfig) -> None:
    target = import_experiment(
        Path(str(cfg.official)), Path(str(cfg.out)), epoch=cfg.epoch, meshes=cfg.meshes, scene=cfg.scene,
        name=cfg.name,
    )  # fmt: skip
    print(f"wrote {target}; generate with: python -m drgan.generate ckpt={Path(str(cfg.out)).resolve()} out=DIR "
          "n_background=0 min_background=0.15")  # fmt: skip


if __name__ == "__main__":
    start(main)
