"""`python -m drgan.pipeline data.dir=DIR name=NAME [annotated=DATASET]`: from a folder of images to particle numbers.

Runs the stages a user would run by hand, each as its own command (``python -m drgan.STAGE``, a child process) into
its own folder under ``out`` (default runs/pipeline/NAME):

    profile/    drgan.profile   the images' polarity, sizes, noise ...; the material in drgan_conf/material/NAME.yaml
    train/      drgan.train     the GAN with that material (material=NAME, found on the pipeline's search path)
    generate/   drgan.generate  500 annotated pairs and real background patches from the best epoch
    segment/    drgan.segment   the segmenter trained on them
    finetune/   drgan.segment   (corrected=DIR only) that segmenter fine-tuned on the user's corrected outlines
    analyze/    drgan.analyze   particles.csv, histograms, overlays of every image of DIR
    evaluate/   drgan.evaluate  (annotated=DATASET only) scores and statistics against its masks

and writes ``report.md`` (what each stage chose and why, with links to its figures) and ``pipeline.json`` (each
stage's command, times and state). The settings a stage gets are its own defaults (the best measured; the pipeline's
config adds a few, conf/pipeline/pipeline.yaml) plus what the command line gives it as ``STAGE.KEY=VALUE``.

Resuming: run the same command again. A stage is done when its process exited 0 (recorded in pipeline.json) and its
main output exists; done stages are skipped, the first that is not resumes (drgan.train and drgan.segment from their
``last.ckpt``, drgan.generate from the pairs already written), so a kill at any moment loses at most the step in
progress. A done stage whose settings have changed since is not rerun silently: the pipeline stops and names the
difference; ``redo=STAGE`` runs that stage and every later one again. Two pipelines on one folder are refused.

Elsewhere than here: ``launcher=slurm`` submits each stage as a SLURM job with its own resources (``slurm.*``),
chained, and returns (drgan.pipeline.submit); ``batch=samples.csv`` runs one pipeline per sample and a study summary
(drgan.pipeline.batch); ``only=STAGE`` runs one stage (what each job does); the word ``status`` shows each stage's
state (and job) without running anything. docs/operations.md, "On a SLURM cluster".

Before any stage runs, the inputs are checked: the folder holds images, the name is usable, every STAGE key names a
stage and composes with that stage's config (a typo fails in seconds, not after the GAN), and the annotated images
are none of the images training reads (compared by content).

The code: drgan.pipeline.runner (the local runner), stage_table (the stages, declared once), settings, stages.
"""

from drgan.pipeline import stage_table
from drgan.pipeline.runner import main, run
from drgan.pipeline.settings import Settings, parse_settings

__all__ = ["STAGES", "Settings", "main", "parse_settings", "run"]


def __getattr__(name: str):
    """``STAGES``: the stages' names in order, read from stage_table.PIPELINE at each read."""
    if name == "STAGES":
        return stage_table.STAGES
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
