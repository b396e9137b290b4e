"""The DiffRenderGAN generator: G(phi_i) = noise(render(FCN(phi_i), scene(phi_i)) [+ stage texture], sigma).

Only the FCN learns. Its outputs set the scene's learned parameters (Principled-BSDF values, or a transmission
scene's background, absorption and floor) and the noise sigma; the
differentiable renderer turns them into an image, and gradients flow back through it to the FCN.
Optionally (``material.background_texture``) the stage pixels also receive the fine texture of a real
background patch: a constant added to the image, so it changes no gradient and no label.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from drgan.core.errors import ConfigError
from drgan.models.regressor import ParameterRegressor
from drgan.scene.protocol import Scene
from drgan.scene.scene import gaussian_kernel


def clamp_straight_through(x: torch.Tensor) -> torch.Tensor:
    """Clamp to [0, 1] in the forward pass, identity in the backward pass.

    A plain clamp has zero gradient wherever a render exceeds 1, which the paper's limits (particle
    base colour up to 5) make common: the discriminator's verdict on a saturated particle then never
    reaches the FCN, and training drifts to brighter and brighter particles.
    """
    return x + (x.clamp(0.0, 1.0) - x).detach()


def grained_noise(
    shape: tuple[int, int], grain_px: float, generator: torch.Generator | None, dtype=torch.float32, device=None
) -> torch.Tensor:
    """(H, W) noise of unit variance: white (``grain_px`` 0) or white noise blurred by a Gaussian of stddev
    ``grain_px`` px, as real detectors' noise is spatially correlated.

    The white field is drawn ``radius`` px larger on each side and blurred without padding, so every pixel has
    the same variance: sum(kernel^2) per axis of the separable blur, sum(kernel^2)^2 in all. Dividing by
    sum(kernel^2) restores unit variance exactly (in expectation), and ``sigma`` keeps meaning the noise's
    standard deviation.
    """
    if grain_px < 0:
        raise ConfigError(f"material.noise_grain_px={grain_px}: expected >= 0 (px)")
    if grain_px == 0:
        return torch.randn(shape, generator=generator, dtype=dtype, device=device)
    kernel = gaussian_kernel(grain_px, dtype, device)
    radius = (len(kernel) - 1) // 2
    white = torch.randn((shape[0] + 2 * radius, shape[1] + 2 * radius), generator=generator, dtype=dtype, device=device)
    rows = torch.nn.functional.conv2d(white[None, None], kernel.view(1, 1, 1, -1))
    blurred = torch.nn.functional.conv2d(rows, kernel.view(1, 1, -1, 1))[0, 0]
    return blurred / kernel.square().sum()


def add_noise(image: torch.Tensor, sigma: torch.Tensor, seed: int | None = None, grain_px: float = 0.0) -> torch.Tensor:
    """clamp -> + sigma * N(0, 1) -> clamp: images stay in [0, 1]; sigma and the render stay differentiable.
    ``seed`` draws the noise from a generator of its own (None: torch's global generator). ``grain_px`` > 0
    correlates the noise spatially (`grained_noise`; still unit variance before sigma)."""
    clean = clamp_straight_through(image)
    generator = None if seed is None else torch.Generator(device=clean.device).manual_seed(int(seed))
    if clean.dim() != 2:
        if grain_px:
            raise ConfigError(f"add_noise: noise grain needs an (H, W) image, got shape {tuple(clean.shape)}")
        noise = torch.randn(clean.shape, generator=generator, dtype=clean.dtype, device=clean.device)
    else:
        noise = grained_noise(tuple(clean.shape), grain_px, generator, clean.dtype, clean.device)
    return clamp_straight_through(clean + sigma * noise)


class BackgroundTexture:
    """The fine structure of real background patches, for the stage pixels of synthetic images.

    Real substrates are not the uniform plane the scene renders: the TiO2 SEM stage shows fibres and
    wrinkles. Each patch minus its Gaussian blur of ``highpass_px`` keeps that structure (and the real
    detector noise) and drops the patch's grey level and slow shading, which the learned stage colour and
    the lights own. A render seed picks one patch and one of its 8 dihedral symmetries, so a seed still
    fixes the whole image. It lowers the FID of the same renders (experiments/tio2_sem/README.md).
    """

    def __init__(self, patches: np.ndarray, highpass_px: float = 8.0):
        from scipy.ndimage import gaussian_filter

        patches = np.asarray(patches, dtype=np.float32)
        if patches.ndim != 3 or len(patches) == 0 or patches.shape[1] != patches.shape[2]:
            raise ConfigError(
                f"material.background_texture: expected square background patches (k, H, H) with k >= 1, got shape "
                f"{patches.shape}; the texture needs data.n_background > 0 (or backgrounds=<run>/patches for generate)"
            )
        if not np.isfinite(patches).all():
            raise ConfigError("material.background_texture: the background patches hold non-finite values")
        if isinstance(highpass_px, bool) or not isinstance(highpass_px, (int, float)) or not highpass_px > 0:
            raise ConfigError(f"material.background_texture.highpass_px={highpass_px!r}: expected a number of px > 0")
        self.highpass_px = float(highpass_px)
        self.textures = np.stack(
            [patch - gaussian_filter(patch, self.highpass_px, mode="reflect") for patch in patches]
        )

    def __len__(self) -> int:
        return len(self.textures)

    @property
    def size(self) -> int:
        return self.textures.shape[-1]

    def for_seed(self, seed: int) -> torch.Tensor:
        """(H, W) texture for the render of ``seed``: patch and symmetry drawn from the seed alone."""
        from drgan.data.patches import dihedral_augment

        rng = np.random.default_rng(int(seed))
        index, symmetry = int(rng.integers(len(self.textures))), int(rng.integers(8))
        return torch.from_numpy(dihedral_augment(self.textures[index], symmetry))


@dataclass
class Sample:
    """One generated image with everything needed to annotate and reproduce it."""

    image: np.ndarray  # (H, W) float32 in [0, 1], noised
    labels: np.ndarray  # (H, W) int32 instance ids, 0 = background
    phi: np.ndarray  # (n, 4) x, y, z, scale in px of the real image
    parameters: dict  # learned and fixed parameter values by key, e.g. "particle.roughness"
    seed: int


class Generator(nn.Module):
    """FCN + scene + noise. ``forward(phi)`` maps (B, n, 4) constellations to (B, 1, H, W) images.

    ``scene`` is any `drgan.scene.protocol.Scene`; the FCN's widths come from the ``model`` group
    (conf/gan/model/diffrendergan.yaml)."""

    def __init__(
        self,
        scene: Scene,
        *,
        hidden: int,
        blocks: int,
        dropout: float,
        seed: int = 0,
        noise_grain_px: float = 0.0,
    ):
        super().__init__()
        if isinstance(noise_grain_px, bool) or not isinstance(noise_grain_px, (int, float)) or not noise_grain_px >= 0:
            raise ConfigError(f"material.noise_grain_px={noise_grain_px!r}: expected a number of px >= 0")
        self.noise_grain_px = float(noise_grain_px)  # stddev of the noise's spatial correlation (`grained_noise`)
        self.scene = scene
        self.material = scene.spec.parameters
        self.learned = self.material.learned
        self.regressor = ParameterRegressor(scene.n_particles, len(self.learned), hidden, blocks, dropout)
        self.register_buffer("view_width", torch.tensor(float(scene.spec.view_width)))
        # Render seeds are derived from a counter saved with the checkpoint, so a resumed run does not
        # replay the sample patterns of its first steps.
        self.register_buffer("render_count", torch.zeros((), dtype=torch.int64))
        self.base_seed = int(seed)
        self.background: BackgroundTexture | None = None  # data, not weights: never in a checkpoint
        # (k,) values used instead of the network's for every image (ablations: drgan.synthetic.source.use_parameters)
        self.fixed_values: torch.Tensor | None = None

    def set_background(self, texture: BackgroundTexture | None) -> None:
        """Add ``texture`` to the stage pixels of every later render (None: the stage as rendered)."""
        if texture is not None and texture.size != self.scene.spec.render.resolution:
            raise ConfigError(
                f"material.background_texture: background patches of {texture.size} px, renders of "
                f"{self.scene.spec.render.resolution} px; they must match (data.patch_size = renderer.resolution)"
            )
        self.background = texture

    def normalise(self, phi: torch.Tensor) -> torch.Tensor:
        return phi / self.view_width

    def learned_values(self, phi: torch.Tensor) -> torch.Tensor:
        """(B, n, 4) -> (B, k): each learned parameter rescaled into its [min, max]."""
        if self.fixed_values is not None:
            return self.fixed_values.to(phi.dtype).expand(phi.shape[0], -1)
        unit = self.regressor(self.normalise(phi))
        low = unit.new_tensor([p.low for p in self.learned])
        high = unit.new_tensor([p.high for p in self.learned])
        return low + (high - low) * unit

    def _split(self, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(k,) -> (BSDF values for the scene, sigma)."""
        n_bsdf = len(self.scene.learned)
        sigma = (
            values[n_bsdf] if self.material.noise_sigma.learned else values.new_tensor(self.material.noise_sigma.value)
        )
        return values[:n_bsdf], sigma

    def next_seed(self) -> int:
        seed = (self.base_seed * 1_000_003 + int(self.render_count)) & 0xFFFFFFFF
        self.render_count += 1
        return seed

    def render_one(
        self, phi_i: torch.Tensor, values: torch.Tensor, seed: int | None = None, spp: int | None = None
    ) -> torch.Tensor:
        """One noised image (1, H, W) of constellation phi_i with learned values (k,); spp None = the scene's."""
        bsdf_values, sigma = self._split(values)
        self.scene.set_layout(phi_i)
        seed = self.next_seed() if seed is None else int(seed)
        radiance = self.scene.render(bsdf_values, seed=seed, spp=spp)
        if self.background is not None:  # stage pixels only: labels and gradients stay those of the render
            like = {"dtype": radiance.dtype, "device": radiance.device}  # the texture is kept on the CPU
            stage = torch.from_numpy(self.scene.instance_labels() == 0).to(**like)
            radiance = radiance + self.background.for_seed(seed).to(**like) * stage
        return add_noise(radiance, sigma, seed=seed, grain_px=self.noise_grain_px).unsqueeze(
            0
        )  # one seed fixes the image: paths, texture, noise

    def render_batch(self, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, n, 4) -> images (B, 1, H, W) and the learned values (B, k) they were rendered with."""
        if phi.dim() == 2:
            phi = phi.unsqueeze(0)
        values = self.learned_values(phi.to(self.view_width.dtype))
        return torch.stack([self.render_one(phi[b], values[b]) for b in range(phi.shape[0])]), values

    def forward(self, phi: torch.Tensor) -> torch.Tensor:
        return self.render_batch(phi)[0]

    def parameter_table(self, values: torch.Tensor) -> dict[str, float]:
        """All parameters of one render by key, learned (from ``values``) and fixed."""
        table = {p.key: float(p.value) for p in self.material.bsdf if not p.learned}
        table.update({p.key: float(v) for p, v in zip(self.learned, values.detach().cpu().tolist())})
        if not self.material.noise_sigma.learned:
            table[self.material.noise_sigma.key] = float(self.material.noise_sigma.value)
        return table

    @torch.no_grad()
    def sample(self, phi_i, seed: int | None = None, spp: int | None = None) -> Sample:
        """Render one constellation without gradients and return image, labels, phi and parameters.

        ``spp`` overrides the training spp (e.g. generate a dataset at a higher spp than was trained at)."""
        phi_i = torch.as_tensor(np.asarray(phi_i), dtype=torch.float32, device=self.view_width.device)
        was_training = self.training
        self.eval()
        try:
            values = self.learned_values(phi_i.unsqueeze(0))[0]
            seed = self.next_seed() if seed is None else int(seed)
            image = self.render_one(phi_i, values, seed=seed, spp=spp)[0]  # the primal render builds no AD graph
            labels = self.scene.instance_labels()
        finally:
            self.train(was_training)
        return Sample(image.cpu().numpy(), labels, phi_i.cpu().numpy(), self.parameter_table(values), seed)
