"""What a drgan.pipeline run chose and found, read back from the files its stages wrote: one summary per stage
(``profile_summary`` ...: a line for the console, numbers for MLflow, the rest for the report; each stage's entry in
stage_table.py names its own) and ``report.md`` (``write_report``), which links every stage's figures and says what each
stage chose and why."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from drgan.core.io import read_csv, write_bytes


def _json(path: Path) -> dict:
    try:
        return json.loads(path.read_text()) if path.is_file() else {}
    except json.JSONDecodeError:
        return {}


def _number(value, fmt: str = "{:.3f}") -> str:
    return fmt.format(value) if isinstance(value, (int, float)) and math.isfinite(value) else "n/a"


def profile_summary(folder: Path) -> dict:
    p = _json(folder / "profile.json")
    if not p:
        return {}
    sizes, polarity, material = p.get("sizes", {}), p.get("polarity", {}), p.get("material", {})
    pixel = p.get("pixel_size") or {}
    return {
        "line": f"{polarity.get('value')} particles, median diameter {_number(sizes.get('median_diameter_px'), '{:.1f}')}"
        f" px ({sizes.get('chosen')}), material from {material.get('parent')}",
        "metrics": {
            "profile/median_diameter_px": sizes.get("median_diameter_px"),
            "profile/particles": (p.get("segmentation") or {}).get("particles"),
        },
        "polarity": polarity.get("value"),
        "median_diameter_px": sizes.get("median_diameter_px"),
        "size_model": sizes.get("chosen"),
        "parent": material.get("parent"),
        "scale_px": (p.get("segmentation") or {}).get("scale_px"),
        "nm_per_px": pixel.get("nm_per_px"),
        "pixel_size_source": pixel.get("source"),
        "images": (p.get("data") or {}).get("images"),
    }


def train_summary(folder: Path) -> dict:
    metrics, best = _json(folder / "metrics.json"), _json(folder / "checkpoints" / "best_epoch.json")
    grey = _json(folder / "grey_start.json")
    if not metrics:
        return {}
    ok = best.get("brightness_ok")
    line = (
        f"stopped ({metrics.get('stop_reason')}) after epoch {metrics.get('epoch', 0) - 1}; best epoch "
        f"{best.get('epoch')}, FID {_number(best.get('fid'), '{:.1f}')}, grey "
        + ("in range" if ok else "OUT of the real range" if ok is not None else "unchecked")
    )
    return {
        "line": line,
        "metrics": {"train/best_fid": best.get("fid"), "train/best_epoch": best.get("epoch")},
        "stop_reason": metrics.get("stop_reason"),
        "stop_message": metrics.get("stop_message"),
        "epochs": metrics.get("epoch"),
        "steps": metrics.get("global_step"),
        "best_epoch": best.get("epoch"),
        "fid": best.get("fid"),
        "brightness_ok": ok,
        "particle_brightness": best.get("particle_brightness"),
        "background_brightness": best.get("background_brightness"),
        "grey_start": {k: grey.get(k) for k in ("real", "first", "last", "steps")} if grey else None,
    }


def generate_summary(folder: Path) -> dict:
    manifest = _json(folder / "manifest.json")
    counts = manifest.get("counts") or {}
    if not counts:
        return {}
    config = manifest.get("config") or {}
    noise = _json(folder / "noise_check.json")
    ratios = {name: (noise.get(name) or {}).get("ratio") for name in ("background", "particles")}
    measured = {name: ratio for name, ratio in ratios.items() if ratio is not None}
    return {
        "line": f"{counts.get('synthetic')} pairs ({counts.get('dropped')} dropped), {counts.get('background')} "
        f"background + {counts.get('partial_background')} partial background windows"
        + ("; fine noise " + ", ".join(f"{k} {v:.2g} x real" for k, v in measured.items()) if measured else ""),
        "metrics": {
            "generate/pairs": counts.get("synthetic"),
            "generate/dropped": counts.get("dropped"),
            **{f"generate/noise_{name}_x_real": ratio for name, ratio in measured.items()},
        },
        "counts": counts,
        "grey_spread": config.get("grey_spread"),
        "spp": (config.get("renderer") or {}).get("spp"),
        "noise": noise or None,
    }


def segment_summary(folder: Path) -> dict:
    metrics = _json(folder / "metrics.json")
    if not metrics:
        return {}
    calibration = metrics.get("split_calibration") or {}
    contact = metrics.get("contact_weight") or {}
    weight = f", contact weight {contact['value']:g} ({contact.get('why')})" if contact.get("value") is not None else ""
    check = metrics.get("closed_loop") or {}
    checked = ""
    if check.get("median_error"):
        checked = (
            f"; on {check.get('n_pairs')} held-out generated pairs median diameter "
            f"{_number((check['median_error'] or {}).get('value'), '{:+.1%}')}, count "
            f"{_number((check.get('count_error') or {}).get('value'), '{:+.1%}')}, edge "
            f"{_number(check.get('edge_offset_px'), '{:+.2f}')} px"
        )
    guard = calibration.get("real_count") or {}
    was = guard.get("from") or {}
    taken = f"the most up to {guard.get('ceiling', 0):g}" if guard.get("side") == "above" else "the count nearest it"
    moved = (
        f" (depth {was['split_depth']} core {was['split_core']} on the generated pairs counted {guard['chosen_count']} "
        f"particles on your images against the classical {guard['classical']}: {taken} kept)"
        if guard.get("moved")
        else ""
    )
    agreement = metrics.get("agreement") or {}
    agreed = f"; {agreement['why']}" if agreement.get("why") else ""
    kept = [a for a in agreement.get("attempts", []) if a.get("attempt") == agreement.get("kept_attempt")]
    return {
        "line": f"{metrics.get('epoch')} epochs ({metrics.get('stop_reason')}), val DSC "
        f"{_number(metrics.get('val/dsc'))}, split depth {calibration.get('split_depth')} core "
        f"{calibration.get('split_core')}{moved}{weight}{checked}{agreed}",
        "metrics": {"segment/val_dsc": metrics.get("val/dsc"), "segment/epochs": metrics.get("epoch")}
        | {k: metrics[k] for k in ("check/median_error", "check/count_error", "check/edge_offset_px") if k in metrics}
        | (
            {"segment/classical_covered": kept[0]["covered"], "segment/attempts": len(agreement["attempts"])}
            if kept
            else {}
        ),
        "val_dsc": metrics.get("val/dsc"),
        "stop_reason": metrics.get("stop_reason"),
        "settled": metrics.get("settled"),
        "split": {k: calibration.get(k) for k in ("split_depth", "split_core", "ap50")} if calibration else None,
    }


def _bracket(cell: dict) -> str:
    """A statistic's 95 % interval as " [low, high]"; "" without one (no bootstrap, one image)."""
    low, high = cell.get("low"), cell.get("high")
    return f" [{_number(low, '{:.1f}')}, {_number(high, '{:.1f}')}]" if isinstance(low, float) and low == low else ""


def analyze_summary(folder: Path) -> dict:
    summary = _json(folder / "summary.json")
    if not summary:
        return {}
    stats, unit = summary.get("statistics") or {}, summary.get("unit", "px")
    count, median = (stats.get(k, {}).get("value") for k in ("count", "median_diameter"))
    model = (stats.get("model") or {}).get("chosen")
    interval = _bracket(stats.get("median_diameter", {}))
    # the profile's sizes and segmentation compared by analyze (profile=); runs before that: the profile's median
    classical = summary.get("classical") or {
        "median_diameter_px": profile_summary(folder.parent / "profile").get("median_diameter_px")
    }
    line = (
        f"{_number(count, '{:.0f}')} particles in {summary.get('images')} images, median diameter "
        f"{_number(median, '{:.1f}')}{interval} {unit}" + (f", {model}" if model else "")
    )
    theirs = classical.get("statistics")
    if summary.get("trusted") == "classical" and theirs:  # the sizes drgan trusts come first in statistics.md too
        cell = theirs["median_diameter"]
        line = (
            f"drgan trusts the classical sizes: median diameter {_number(cell.get('value'), '{:.1f}')}"
            f"{_bracket(cell)} {unit} ({_number(theirs['count']['value'], '{:.0f}')} particles in "
            f"{classical.get('images')} images, the profile's threshold + watershed at half contrast); the "
            f"segmenter's: {line}"
        )
    return {
        "closed_loop": summary.get("closed_loop"),
        "median_diameter_px": summary.get("median_diameter_px"),
        "classical": classical,
        "trusted": summary.get("trusted"),
        "verdict": summary.get("verdict"),
        "line": line,
        "metrics": {"analyze/particles": count, f"analyze/median_diameter_{unit}": median}
        | ({f"analyze/classical_median_diameter_{unit}": theirs["median_diameter"]["value"]} if theirs else {}),
        "particles": count,
        "median_diameter": median,
        "unit": unit,
        "size_model": model,
    }


def evaluate_summary(folder: Path) -> dict:
    means = [r for r in read_csv(folder / "results.csv")[0] if r.get("image") == "mean"]
    if not means:
        return {}
    scores = {k: float(means[0][k]) for k in ("dsc", "ap50", "pq") if means[0].get(k)}
    rows = read_csv(folder / "statistics.csv")[0]
    stats = {r["statistic"]: float(r["value"]) for r in rows if r.get("run") == "run0"}
    source = _json(folder / "reported.json")  # which table the run "reported" holds (evaluate reported=)
    reported = (
        {r["statistic"]: float(r["value"]) for r in rows if r.get("run") == "reported"}
        if source.get("table") == "classical"  # else it repeats the segmenter's own numbers
        else {}
    )
    line = f"DSC {_number(scores.get('dsc'))}, AP50 {_number(scores.get('ap50'))}, PQ {_number(scores.get('pq'))}"
    if "median_error" in stats:
        line += f"; median diameter {100 * stats['median_error']:+.1f} %, count {100 * stats['count_error']:+.1f} %"
    if "median_error" in reported:  # the sizes analyze reported (its trusted table), when not the segmenter's own
        line += (
            f"; the sizes the report gives (the classical ones): median diameter {100 * reported['median_error']:+.1f}"
            f" %, count {100 * reported['count_error']:+.1f} %"
        )
    return {
        "line": line,
        "metrics": {f"evaluate/{k}": v for k, v in scores.items()}
        | {f"evaluate/{k}": stats[k] for k in ("median_error", "count_error") if k in stats}
        | {f"evaluate/reported_{k}": reported[k] for k in ("median_error", "count_error") if k in reported},
        "scores": scores,
        "statistics": {k: stats[k] for k in ("median_error", "count_error", "ks", "w1") if k in stats},
    }


def analyze_details(summary: dict, settings) -> list[str]:
    """The analyze stage's report lines: how far its sizes can be trusted (the segmenter's closed-loop check) and how
    they compare with the profile's classical ones (drgan.segmenters.classical_check)."""
    from drgan.segmenters.classical_check import compare_with_classical
    from drgan.segmenters.closed_loop import trust_line

    if not summary:
        return []
    check = summary.get("closed_loop")
    # a pipeline state written before analyze compared the segmentations holds the profile's median only
    classical = summary.get("classical") or {"median_diameter_px": summary.get("classical_median_px")}
    lines = [f"- how far these sizes can be trusted: {trust_line(check)}" if check else (
        "- how far these sizes can be trusted: the segmenter has no closed-loop check (no held-out generated pairs)"
    )]  # fmt: skip
    lines.append(
        "- against the profile: "
        + (  # as analyze judged it; runs from before it stored its verdict: judged again
            summary.get("verdict")
            or compare_with_classical(
                summary.get("median_diameter_px"), classical.get("median_diameter_px"), check, classical
            )
        )
    )
    return lines


# --- report.md ---------------------------------------------------------------------------------------------


def _relative(path: Path, root: Path) -> str:
    return os.path.relpath(path, root)


def train_details(summary: dict, settings) -> list[str]:
    """The GAN's report lines below its result: why it stopped, the chosen epoch's grey, the grey start."""
    lines = []
    if summary.get("stop_message"):
        lines.append(f"- why it stopped: {summary['stop_message']}")
    if summary.get("particle_brightness") is not None:
        lines.append(
            f"- the chosen epoch's grey / the real patches': particles {_number(summary['particle_brightness'])} x, "
            f"background {_number(summary['background_brightness'])} x"
            + ("" if summary.get("brightness_ok") else " (outside the range the real patches span: see the log)")
        )
    grey = summary.get("grey_start")
    if grey and grey.get("real"):
        lines.append(
            "- grey start: "
            + ", ".join(
                f"{k} {_number((grey.get('first') or {}).get(k))} -> {_number((grey.get('last') or {}).get(k))} "
                f"(real {_number(grey['real'].get(k))})"
                for k in ("particle", "background", "noise")
            )
            + f" in {grey.get('steps')} steps"
        )
    return lines


def profile_details(summary: dict, settings) -> list[str]:
    """The profile's report lines below its result: the material it wrote, the pixel size it read."""
    if not summary.get("parent"):
        return []
    out = settings.out
    return [
        f"- the material: `{_relative(out / 'drgan_conf' / 'material' / (settings.name + '.yaml'), out)}` "
        f"(inherits `{summary['parent']}`; every measured key says why it was set)",
        f"- pixel size: {summary.get('nm_per_px') or 'unknown'} nm/px ({summary.get('pixel_size_source')})",
    ]


def write_report(settings, state: dict, stages) -> None:
    """report.md of the pipeline folder: per stage what it does, its state, time, result line, links, command."""
    out = settings.out
    lines = [
        f"# drgan pipeline `{settings.name}`",
        "",
        f"Images: `{settings.data_dir}` ({(state.get('inputs') or {}).get('images')} images, "
        f"{(state.get('inputs') or {}).get('training_images')} of them train the profile and the GAN)"
        + (f"; scored against `{settings.annotated}`" if settings.annotated else "")
        + ".",
        "",
        "Rerun the same command to resume; `redo=STAGE` runs a stage and the later ones again. Each stage's folder is "
        "what its own command writes (`python -m drgan.STAGE`, the command below), so any stage can be rerun by hand.",
        "",
        "| stage | state | time | result |",
        "|---|---|---|---|",
    ]
    for stage in stages:
        record = (state.get("stages") or {}).get(stage.name, {})
        summary = record.get("summary") or {}
        seconds = record.get("seconds")
        time_text = "" if seconds is None else (f"{seconds / 60:.1f} min" if seconds >= 120 else f"{seconds:.0f} s")
        lines.append(
            f"| [{stage.name}](#{stage.name}) | {record.get('state', 'to do')} | {time_text} | {summary.get('line', '')} |"
        )
    for stage in stages:
        record = (state.get("stages") or {}).get(stage.name, {})
        summary = record.get("summary") or {}
        lines += ["", f"## {stage.name}", "", stage.spec.what + "."]
        if summary.get("line"):
            lines += ["", f"**{summary['line']}**"]
        details = stage.spec.details(summary, settings)
        if details:
            lines += ["", *details]
        links = [
            f"[{label}]({_relative(stage.folder / rel, out)})" for label, rel in stage.spec.links
            if (stage.folder / rel).exists()
        ]  # fmt: skip
        if links:
            lines += ["", "Look at: " + ", ".join(links) + "."]
        lines += ["", "```", f"python -m {stage.module} " + " ".join(stage.recorded()), "```"]
    text = "\n".join(lines) + "\n"
    write_bytes(out / "report.md", text.encode())
    write_bytes(out / "report.html", report_html(text, out, f"drgan pipeline {settings.name}").encode())


def report_html(text: str, out: Path, title: str) -> str:
    """report.html: report.md with its figures embedded, then analyze's overlays and particle table (drgan.core.html)."""
    from drgan.core.html import markdown_html, page, particles_and_overlays

    body = markdown_html(text, out)
    if (out / "analyze" / "particles.csv").is_file():
        body += particles_and_overlays(out / "analyze")
    return page(title, body)
