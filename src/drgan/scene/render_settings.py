"""The ``renderer`` config group, typed: `RenderSettings`, how well a scene is rendered (its quality and cost), never
what the scene is (``material``: the physics).

The one source of every renderer key: a field here is its type, its default and its check (`__post_init__`, a
ConfigError naming ``renderer.KEY``). `drgan.launch.configs` derives the group's compose-time schema from these fields
(`renderer_fields`, in this order, which is the order composed configs list them in), so a new key is one field here
plus, where users should see it, its line in ``conf/gan/renderer/default.yaml`` with the same default and its
comment (tests/test_settings_source.py compares the two). A field another group sets names that group in its
metadata (``filter_stddev``: the material's, the instrument's blur) and is no key of ``renderer``.

Nothing here imports Mitsuba, so composing a config does not start the renderer; `drgan.scene.scene` imports all of
it from here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from drgan.core.errors import ConfigError, check_spp

# direct_light, direct_light_mis: drgan.scene.direct, direct illumination with a one-pass adjoint (max_depth 2 only);
# _mis samples the BSDF as well as the lights on every surface (prb's estimator), direct_light only where it pays
# (`ParticleScene._bsdf_sampled_shapes`)
INTEGRATORS = ("prb_basic", "direct_projective", "prb", "direct_light", "direct_light_mis")
DIRECT_INTEGRATORS = ("direct_light", "direct_light_mis")
GRAD_SEEDS = ("independent", "same")  # renderer.grad_seed: see RenderSettings and `adjoint_seed`


@dataclass(frozen=True)
class RenderSettings:
    integrator: str = "direct_light_mis"  # conf/gan/renderer/default.yaml says why
    max_depth: int = 2  # 2 = direct illumination, all that BSDF-parameter gradients need here
    resolution: int = 256  # pixels per side of the render
    spp: int = 16  # samples per pixel; a perfect square (stratified sampler)
    # samples per pixel of the adjoint (gradient) pass; None = spp. The adjoint of `prb` traces its own
    # paths, so fewer samples give an unbiased gradient of the same image, only noisier (see `render`).
    grad_spp: int | None = None
    # Which samples the adjoint (gradient) pass uses, i.e. which gradient estimator training gets (`adjoint_seed`):
    # "independent": a seed derived from, and never equal to, the image's seed. Its gradient is unbiased for
    #   the derivative of the *expected* image: E[grad] = E[dL/dI(I_noisy)] . dE[I]/dtheta. For a linear loss
    #   that is the exact gradient of E[L(I)] = L(E[I]); for a non-linear loss it is the gradient of neither
    #   L(E[I]) nor E[L(I_noisy)] (the chain rule's first factor is still taken at the noisy image), but it
    #   carries no term from the Monte Carlo grain itself. Mitsuba's choice for inverse rendering
    #   (`mi.render` refuses seed_grad == seed).
    # "same": the image's own seed. With grad_spp == spp the adjoint replays the
    #   image's own paths, so for parameters that do not steer sampling (colours, sheen) the gradient is the
    #   derivative of the realised noisy image, unbiased for d/dtheta E[L(I_noisy)], the expected loss of noisy
    #   renders, grain included: the generator is also rewarded for reshaping its own sampling noise. For
    #   roughness, which steers BSDF sampling, Mitsuba's adjoint holds the sampled directions fixed, so the
    #   replay is unbiased for neither objective in general. With grad_spp < spp the adjoint replays only part
    #   of the image's samples (by accident of the sampler). Numbers: experiments/gradient_estimator/README.md.
    # Default "independent" (experiments/gradient_estimator/README.md): "same" follows the grain term, which at spp 4
    # reverses the sign of the particle colour's gradient, and its trainings dimmed the images faster.
    grad_seed: str = "independent"
    camera_distance: float = 10.0  # x view_width; far camera = nearly orthographic view
    # Gaussian reconstruction filter, in render pixels: the material's ``filter_stddev`` (the instrument's blur,
    # drgan.models.build.render_settings), so no key of the renderer group
    filter_stddev: float = field(default=0.5, metadata={"group": "material"})

    def __post_init__(self):
        check_spp(self.spp, "renderer.spp")
        if self.grad_spp is not None:
            check_spp(self.grad_spp, "renderer.grad_spp")
        if self.grad_seed not in GRAD_SEEDS:
            raise ConfigError(f"renderer.grad_seed={self.grad_seed!r}: expected one of {', '.join(GRAD_SEEDS)}")
        if int(self.resolution) < 1:
            raise ConfigError(f"renderer.resolution={self.resolution}: expected a positive integer")
        if not (self.filter_stddev > 0 and math.isfinite(self.filter_stddev)):
            raise ConfigError(f"renderer.filter_stddev={self.filter_stddev}: expected a positive number")
        if self.integrator not in INTEGRATORS:
            raise ConfigError(f"renderer.integrator={self.integrator!r}: expected one of {', '.join(INTEGRATORS)}")
        if self.max_depth < 2:
            raise ConfigError(f"renderer.max_depth={self.max_depth}: expected >= 2 (1 sees only emitters)")
        if self.integrator in DIRECT_INTEGRATORS and self.max_depth != 2:
            raise ConfigError(
                f"renderer.max_depth={self.max_depth}: renderer.integrator={self.integrator} computes direct "
                "illumination only (max_depth 2); use renderer.integrator=prb for more bounces"
            )
        if self.camera_distance <= 1.0:
            raise ConfigError(f"renderer.camera_distance={self.camera_distance}: expected > 1 (x view_width)")


def renderer_fields(settings: type = RenderSettings) -> tuple[dataclasses.Field, ...]:
    """The fields of ``settings`` (`RenderSettings` or a subclass) that are keys of the ``renderer`` group, in order:
    every one but those whose metadata names another group."""
    return tuple(f for f in dataclasses.fields(settings) if f.metadata.get("group", "renderer") == "renderer")
