"""drgan's Hydra configs: one root per family of entry points (gan/, segmentation/) and the groups they share
(common/, on both roots' search path as ``pkg://drgan.conf.common``). A package only so that Hydra finds common/."""
