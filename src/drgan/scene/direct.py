"""``direct_light``: a differentiable integrator for direct illumination only, with a one-pass adjoint.

drgan's scenes are lit by area emitters (the ring light and the top light) and need one bounce: camera ray ->
surface -> light. Mitsuba's ``prb`` at ``max_depth`` 2 computes the same image, but as a general path tracer:
its adjoint pass first replays every path in primal mode to recover the radiance arriving at each vertex,
then traces it again to backpropagate, i.e. three passes of rays per training iteration (image, replay,
adjoint). At depth one nothing arrives from further along the path, so the adjoint needs no replay: it
re-traces the same rays once with the BSDF evaluations on the AD graph.

Per camera sample (the estimator of ``prb`` with max_depth 2, so the same image in expectation and the same
noise):

- Le of an emitter the camera sees directly;
- light sampling: one point on an emitter (``Scene.sample_emitter_direction``) and its shadow ray,
  f(wi, wo) cos / p_light, weighted by the power heuristic against the BSDF's pdf of that direction;
- BSDF sampling: one direction from the BSDF, one ray; if it hits an emitter, Le f cos / p_bsdf, weighted by
  the power heuristic against the light pdf of that point. The BSDF strategy matters for the principled
  BSDF at low roughness (the learned range reaches 0.01, a near-mirror lobe): light sampling alone would
  hit such a lobe with the top light's reflection rarely and then with a huge weight (fireflies).

Gradients: only BSDF parameters are differentiated (drgan moves no geometry). The sampled directions, pdfs
and MIS weights are held at the current parameters (detached) and f cos is re-evaluated on the AD graph.
This is unbiased for the derivative of the expected image: for samples drawn at theta0, the estimator
sum_s f_theta(w_s) Le w_s(theta0) / p_s(theta0) has expectation I(theta) for every theta, as the MIS weights
of the two strategies sum to one at each direction.

Rays are most of a render's time (``benchmarks/render_parts.py``), so none is traced that cannot add light; the
images are those of tracing them all (and the gradients, up to the order of their sums):

- the shadow ray of a light sample, not where the point on the emitter faces away or where the BSDF is zero (a
  BSDF without transmission, the light behind the surface);
- the BSDF-sampled ray, only if it hits the emitters' geometry (``emitter_culling``, on by default on the CPU):
  a second, tiny scene holds that geometry alone (the emitters' triangles; a box around any other shape); a ray
  that misses it misses every emitter (38 % of them in the TiO2 SEM scene). Scenes with an environment emitter
  are not culled, nor are renders on the GPU (OptiX answers one scene per kernel).

Each saves ~6 % of a render at spp 16 (experiments/benchmarks/train_step.md, "Fewer rays").
"""

from __future__ import annotations

import numpy as np

from drgan.core import backend
from drgan.scene.mitsuba_shapes import mitsuba_mesh

dr = backend.dr
mi = backend.mi

NAME = "direct_light"
_registered: set[str] = set()


def power_heuristic(pdf_a, pdf_b):
    """Veach's power heuristic (beta 2) of strategy a against b; 0 where it is undefined (both pdfs 0)."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    total = a2 + b2
    return dr.select(total > 0, a2 / dr.select(total > 0, total, 1.0), 0.0)


def emitter_geometry(scene):
    """A scene holding only the geometry of ``scene``'s emitters, or None when a ray could reach an emitter
    without hitting any geometry (an environment emitter).

    A mesh emitter is copied triangle for triangle (the same vertices, so a ray hits the copy wherever it hits
    the original); any other emitter shape (sphere, disk, ...) becomes the box of its bounds, a little larger.
    Delta emitters (point, spot, directional) are left out: no ray hits them.
    """
    for emitter in scene.emitters():
        if not mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta) and emitter.get_shape() is None:
            return None  # environment or other infinite emitter
    shapes = {}
    # The scene's shapes, not the emitters' get_shape(): that may return a plain Shape without the mesh buffers.
    for k, shape in enumerate(s for s in scene.shapes() if s.emitter() is not None):
        if shape.is_mesh():
            vertices, faces = np.array(shape.vertex_positions_buffer()), np.array(shape.faces_buffer())
        else:
            box = shape.bbox()
            lo, hi = np.array(box.min, dtype=np.float64), np.array(box.max, dtype=np.float64)
            pad = 1e-4 * max(float(np.max(hi - lo)), 1.0)
            vertices, faces = np.where(_BOX_CORNERS, hi + pad, lo - pad), _BOX_FACES
        name = f"emitter_{k}"
        shapes[name] = mitsuba_mesh(name, vertices.reshape(-1, 3), faces.reshape(-1, 3), normals=False)
    return mi.load_dict({"type": "scene", **shapes})


def _geometry_key(scene) -> tuple:
    """What `emitter_geometry` depends on: the emitters' flags and their shapes (a mesh's vertices and faces, else
    its bounds)."""
    key: list = [tuple(int(e.flags()) for e in scene.emitters())]
    for shape in scene.shapes():
        if shape.emitter() is None:
            continue
        if shape.is_mesh():
            buffers = (shape.vertex_positions_buffer(), shape.faces_buffer())
            geometry = tuple(hash(np.array(b).tobytes()) for b in buffers)
        else:
            geometry = (tuple(shape.bbox().min), tuple(shape.bbox().max))
        key.append((shape.id(), geometry))
    return tuple(key)


# The box's corner i is (x, y, z) = bits (0, 1, 2) of i (1: the upper bound); its 12 triangles face outwards.
_BOX_CORNERS = (np.arange(8)[:, None] >> np.arange(3) & 1).astype(bool)
_BOX_FACES = np.array(
    [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
     [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]],
    dtype=np.uint32,
)  # fmt: skip


def register() -> str:
    """Register ``direct_light`` with Mitsuba for the current variant (idempotent); returns its name."""
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("set a Mitsuba variant (drgan.core.backend.use_variant) before registering direct_light")
    if variant not in _registered:
        cls = _integrator_class()
        mi.register_integrator(NAME, lambda props: cls(props))
        _registered.add(variant)
    return NAME


def _integrator_class():
    """The integrator class for the current variant (Mitsuba's Python base classes are per variant).

    Long because the class is defined inside it: its base exists only once a variant is set, so the class body (the
    sampling routine, the one-pass adjoint, the recapture term) cannot live at module level."""

    from mitsuba.ad.integrators.common import ADIntegrator

    class DirectLightIntegrator(ADIntegrator):
        """Direct illumination from area emitters, light + BSDF sampling with MIS, one-pass adjoint.

        Rendering and the forward derivative come from ``ADIntegrator``. ``render_backward`` is one pass: the
        adjoint radiance of every sample (through the film's splatting, linear in the sample's value), then
        ``sample`` with AD enabled and ``dr.backward_from(δL * L)`` before anything is evaluated, so the
        primal and adjoint arithmetic run as one kernel and no intermediate is stored per sample.
        """

        def __init__(self, props):
            if "max_depth" not in props:
                props["max_depth"] = 2
            super().__init__(props)
            if self.max_depth != 2:
                raise ValueError(
                    f"{NAME}: max_depth={self.max_depth}; this integrator computes direct "
                    "illumination only (max_depth 2)"
                )
            # Shapes (ids, comma-separated; "*" = all) whose points also sample their BSDF (MIS); elsewhere
            # light sampling alone, one ray fewer per sample.
            ids = str(props.get("bsdf_sampling", "*"))
            self.bsdf_sampling = None if ids.strip() == "*" else {i.strip() for i in ids.split(",") if i.strip()}
            # Trace a BSDF-sampled ray through the scene only if it hits an emitter's geometry (module docstring).
            # CPU (Embree) only: OptiX drops a ray query on a second scene inside one kernel (another shader
            # binding table), which would lose light silently.
            cuda = mi.variant().startswith("cuda")
            self.emitter_culling = bool(props.get("emitter_culling", not cuda))
            if cuda and self.emitter_culling:
                raise ValueError(f"{NAME}: emitter_culling needs a CPU (llvm) variant; {mi.variant()} is set")
            self._emitters = (None, None)  # (_geometry_key, emitter_geometry) of the last scene rendered
            # Secondary electrons recaptured (`escape`): the share of the electrons a surface emits towards another
            # surface that are lost to the detector; 0 = none (no ray, no random number: the images of before).
            self.recapture = float(props.get("recapture", 0.0))
            if not 0.0 <= self.recapture <= 1.0:
                raise ValueError(f"{NAME}: recapture={self.recapture}; expected a share in [0, 1]")

        def _emitter_geometry(self, scene):
            """`emitter_geometry` of ``scene``, rebuilt only when its emitters changed."""
            key = _geometry_key(scene)
            if self._emitters[0] != key:
                self._emitters = (key, emitter_geometry(scene))
            return self._emitters[1]

        def _bsdf_sampled(self, scene, si, active):
            """Mask of the points whose BSDF is sampled (``bsdf_sampling``)."""
            if self.bsdf_sampling is None:
                return mi.Bool(active)
            chosen = [shape for shape in scene.shapes() if shape.id() in self.bsdf_sampling]
            missing = self.bsdf_sampling - {shape.id() for shape in chosen}
            if missing:
                raise ValueError(f"{NAME}: bsdf_sampling names shapes the scene lacks: {sorted(missing)}")
            mask = mi.Bool(False)
            for shape in chosen:
                mask |= si.shape == mi.ShapePtr(shape)
            return active & mask

        def escape(self, scene, sampler, ray, si, valid):
            """Per sample, 1 - ``recapture`` where one cosine-distributed direction from the visible point (a
            secondary electron leaving the surface on the camera's side) meets another surface before it escapes,
            else 1: in expectation 1 - recapture x the share of the point's hemisphere that other surfaces cover.
            A crevice between touching particles, half covered by the neighbour, images darker than a free top, as
            SEM contacts do (its own random numbers, drawn after the others'; no gradient: geometry is fixed)."""
            n = dr.select(dr.dot(si.n, ray.d) < 0, si.n, -si.n)
            d = mi.Frame3f(n).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d(valid)))
            hit = scene.ray_intersect(si.spawn_ray(d), ray_flags=mi.RayFlags.Minimal, coherent=False, active=valid)
            blocked = valid & hit.is_valid() & (hit.emitter(scene, valid) == None)  # noqa: E711  (an emitter: escaped)
            return dr.select(blocked, 1.0 - self.recapture, 1.0)

        def to_string(self):
            return f"DirectLightIntegrator[{NAME}, max_depth = 2]"

        def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            film = sensor.film()
            with dr.suspend_grad():
                sampler, spp = self.prepare(sensor, seed, spp, self.aov_names())
                ray, weight, pos = self.sample_rays(scene, sensor, sampler)
                with dr.resume_grad():
                    # δL of each sample: backpropagate grad_in through splatting and the weight division.
                    unit = dr.full(mi.Spectrum, 1.0, dr.width(ray))
                    dr.enable_grad(unit)
                    block = film.create_block()
                    block.set_coalesce(block.coalesce() and spp >= 4)
                    ADIntegrator._splat_to_block(
                        block,
                        film,
                        pos,
                        value=unit * weight,
                        weight=1.0,
                        alpha=1.0,
                        aovs=[],
                        wavelengths=ray.wavelengths,
                    )
                    film.put_block(block)
                    image = film.develop()
                    dr.set_grad(image, grad_in)
                    dr.enqueue(dr.ADMode.Backward, image)
                    dr.traverse(dr.ADMode.Backward)
                    δL = dr.grad(unit)
                film.clear()
                self.sample(dr.ADMode.Backward, scene, sampler, ray, δL=δL, active=mi.Bool(True))
                del sampler, ray, weight, pos, block, image, unit, δL
                dr.eval()

        def sample(
            self, mode, scene, sampler, ray, depth=None, δL=None, δaovs=None, state_in=None, active=True, **kwargs
        ):
            differentiate = mode != dr.ADMode.Primal
            ctx = mi.BSDFContext()
            with dr.suspend_grad():
                ray = mi.Ray3f(ray)
                active = mi.Bool(active)
                si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active)
                valid = active & si.is_valid()
                # Emitters the camera sees directly (count once: this is the path of depth 0).
                L = si.emitter(scene, valid).eval(si, valid)

                bsdf = si.bsdf(ray)
                smooth = valid & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)

                # Light sampling (em_weight = Le / p_light), then the shadow ray, traced only where the sample can
                # add light: not where the point on the emitter faces away, nor where a BSDF without
                # transmission is zero (the light behind the surface): ~6 % of a render, the same image to the bit
                # (and gradient, to the order of the sums). The side test uses si's shading frame: a BSDF that
                # turns that frame itself (normalmap, bumpmap; none in drgan's scenes) could be lit from behind it.
                ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(valid), False, smooth)
                wo_light = si.to_local(ds.d)
                light_ok = smooth & (ds.pdf > 0) & dr.any(em_weight != 0.0)
                reflects = ~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)
                light_ok &= ~reflects | (mi.Frame3f.cos_theta(si.wi) * mi.Frame3f.cos_theta(wo_light) > 0)
                light_ok &= ~scene.ray_test(si.spawn_ray_to(ds.p), False, light_ok)

                # BSDF sampling and the ray it spawns (the same random numbers are drawn either way).
                sampled = self._bsdf_sampled(scene, si, valid)
                bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(valid), sampler.next_2d(valid), sampled)
                bsdf_ok = sampled & (bs.pdf > 0)
                ray_b = si.spawn_ray(si.to_world(bs.wo))
                cull = self.emitter_culling and not mi.variant().startswith("cuda")  # (see __init__)
                emitters = self._emitter_geometry(scene) if cull else None
                if emitters is not None:
                    bsdf_ok &= emitters.ray_test(ray_b, False, bsdf_ok)
                # Only the emitter it may hit is read at this point (its radiance and pdf: position and normal), so
                # no UV, shading frame or their derivatives: ~15 % of a render at spp 16 (image unchanged).
                si_b = scene.ray_intersect(ray_b, ray_flags=mi.RayFlags.Minimal, coherent=False, active=bsdf_ok)
                emitter_b = si_b.emitter(scene, bsdf_ok)
                hit_light = bsdf_ok & (emitter_b != None)  # noqa: E711  (a Dr.Jit pointer array: per-lane test)
                ds_b = mi.DirectionSample3f(scene, si_b, si)
                delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                pdf_light_b = scene.pdf_emitter_direction(si, ds_b, hit_light & ~delta)
                Le_b = emitter_b.eval(si_b, hit_light)
                mis_b = dr.select(delta, 1.0, power_heuristic(bs.pdf, pdf_light_b))
                escape = self.escape(scene, sampler, ray, si, valid) if self.recapture > 0 else None

            with dr.resume_grad(when=differentiate):
                f_light, pdf_bsdf_light = bsdf.eval_pdf(ctx, si, wo_light, light_ok)
                pdf_bsdf_light = dr.detach(pdf_bsdf_light)
                mis_light = dr.select(ds.delta | ~sampled, 1.0, power_heuristic(ds.pdf, pdf_bsdf_light))
                L += dr.select(light_ok, em_weight * mis_light * f_light, 0.0)
                if differentiate:
                    # f cos / p on the AD graph, p held (the sample was drawn at the current parameters).
                    inv_pdf = dr.select(bs.pdf > 0, dr.rcp(bs.pdf), 0.0)
                    weight_b = bsdf.eval(ctx, si, bs.wo, hit_light) * inv_pdf
                    weight_b = dr.replace_grad(bsdf_weight, weight_b)
                else:
                    weight_b = bsdf_weight
                L += dr.select(hit_light, Le_b * mis_b * weight_b, 0.0)
                if escape is not None:
                    L *= escape
                if mode == dr.ADMode.Backward and δL is not None:
                    dr.backward_from(δL * L)
            return dr.detach(L) if mode == dr.ADMode.Backward and δL is not None else L, valid, [], None

    return DirectLightIntegrator
