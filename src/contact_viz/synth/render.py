"""Rendering of a stereo pair by open3d ray casting and shading (``Renderer``); open3d is imported
when a renderer is built."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from contact_viz.synth.motion import ToolTrack, LAYOUTS
from contact_viz.synth.params import REFERENCE_WIDTH_PX, SynthParams
from contact_viz.synth.scene import StereoCamera, TissueFrame, phantom_height, surface_points
from contact_viz.synth.tools import Primitive, tool_primitives


@dataclass(frozen=True)
class _Material:
    albedo: tuple[float, float, float]  # diffuse reflectance, linear RGB
    gloss: float  # broad specular weight, -
    gloss_squarings: int  # broad specular exponent = 2**gloss_squarings
    shine: float  # sharp specular weight, -
    shine_squarings: int  # sharp specular exponent = 2**shine_squarings


_SHAFT = _Material((0.26, 0.27, 0.29), 0.7, 4, 0.9, 6)  # brushed steel
_WRIST = _Material((0.05, 0.05, 0.055), 0.3, 5, 0.6, 7)  # dark anodized wrist
_JAW = _Material((0.085, 0.085, 0.09), 0.35, 5, 0.7, 7)  # dark jaws
_TOOL_MATERIALS = (_SHAFT, _WRIST, _JAW)
_TISSUE = _Material((0.0, 0.0, 0.0), 0.10, 4, 1.3, 8)  # moist tissue; albedo comes from the texture, weights x wetness
_BUMP_SLOPE = 0.05  # std of the micro-relief slope that breaks highlights into wet glints, -
_BUMP_CELL_M = 0.0012  # size of the micro-relief bumps, m
_AMBIENT = 0.03  # ambient light, fraction of the light at the tissue distance
_EXPOSURE = 0.8  # gain before the tone curve, -
_SHOULDER = 0.6  # tone curve y = (1 + s) x / (1 + s x): soft roll-off of bright tissue, s
_VIGNETTE = 0.45  # vignetting (1 + a r^2/f^2)^-2, a
_MAX_CELL_M = 0.002  # coarsest tissue mesh cell (resolves the dent at small image sizes), m
_TEXEL_PX = 1.5  # texture texel size as seen at the tissue distance, px
_MAX_TEXTURE_PX = 4096  # largest texture side, texels
_GRAZING_SLOPE = 4.0  # depth slope (dz per lateral m) beyond which a lattice cell counts as a depth edge, -
_CYL_SEGMENTS = 48  # facets around a cylinder, count
_SPHERE_RES = 16  # open3d sphere resolution, count


_Part = Primitive  # one primitive of a tool (synth.tools)


def tool_parts(track: ToolTrack, index: int, params: SynthParams) -> list[_Part]:
    """The tool of frame ``index`` as primitives: shaft, wrist and two capsule jaws."""
    return tool_primitives(track, index, params)


def _value_noise(rng, shape, cell_texels: float) -> np.ndarray:
    """Smooth random field (shape) float32 of unit std varying over ~cell_texels."""
    h, w = shape
    gh, gw = max(2, int(h / cell_texels) + 3), max(2, int(w / cell_texels) + 3)
    small = rng.standard_normal((gh, gw)).astype(np.float32)
    field = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    return field / max(float(field.std()), 1e-6)


def _vessel_map(rng, shape, texel_m: float, count: int) -> np.ndarray:
    """Vessel density (shape) float32 in [0, 1]: branching tapered random walks plus capillaries."""
    h, w = shape
    canvas = np.zeros((h, w), np.float32)
    step_m = 0.001  # walk step, m
    sub = 4  # cv2 sub-pixel factor (shift = 2 bits)
    stack = []
    for _ in range(count):
        stack.append((rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0, 2 * np.pi),
                      rng.uniform(0.0006, 0.0012), rng.uniform(0.05, 0.1), 1.0))
    for _ in range(count * 10):  # capillaries
        stack.append((rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0, 2 * np.pi),
                      rng.uniform(0.0001, 0.0002), rng.uniform(0.006, 0.02), 0.55))
    while stack:
        x, y, heading, width_m, length_m, strength = stack.pop()
        steps = max(2, int(length_m / step_m))
        for k in range(steps):
            heading += rng.normal(0.0, 0.15)
            nx = x + math.cos(heading) * step_m / texel_m
            ny = y + math.sin(heading) * step_m / texel_m
            taper = width_m * (1.0 - 0.5 * k / steps)
            thick = max(1, round(taper / texel_m))
            start, end = (round(x * sub), round(y * sub)), (round(nx * sub), round(ny * sub))
            cv2.line(canvas, start, end, strength, thick, cv2.LINE_AA, 2)
            x, y = nx, ny
            if width_m > 0.0003 and rng.uniform() < 0.06:
                stack.append((x, y, heading + rng.choice([-1, 1]) * rng.uniform(0.4, 1.0),
                              taper * 0.6, length_m * 0.5, strength * 0.9))
    blur = max(0.5, 0.00012 / texel_m)
    return np.clip(cv2.GaussianBlur(canvas, (0, 0), blur), 0.0, 1.0)


def _tissue_texture(phantom: str, u_grid: np.ndarray, v_grid: np.ndarray, rng):
    """Surface maps over the (u, v) texel grid (T, S) (phantom units; the lengths here are phantom units
    too): albedo (T, S, 3) float32 linear RGB, wetness (T, S) float32 in [0, 1], and micro-relief slopes
    (dh/du, dh/dv) (T, S, 2) float32."""
    layout = LAYOUTS[phantom]
    texel_m = float(u_grid[1] - u_grid[0])
    shape = (len(v_grid), len(u_grid))
    height = phantom_height(phantom, u_grid[None, :], v_grid[:, None])
    on_phantom = np.clip((height - 0.0005) / 0.0025, 0.0, 1.0).astype(np.float32)[..., None]
    blotch = _value_noise(rng, shape, 0.012 / texel_m)
    mottle = _value_noise(rng, shape, 0.003 / texel_m)
    grain = _value_noise(rng, shape, 0.0008 / texel_m)
    tint = np.clip(_value_noise(rng, shape, 0.02 / texel_m), -1.5, 1.5)[..., None]
    vessels = _vessel_map(rng, shape, texel_m, layout.vessel_count)
    shade = (1.0 + 0.14 * blotch + 0.06 * mottle + 0.025 * grain)[..., None]
    redder = np.array([0.04, -0.10, -0.08], np.float32)  # tint toward deeper red per unit of tint noise
    phantom_rgb = np.asarray(layout.tissue_rgb, np.float32) * (1.0 + redder * tint)
    tray_rgb = np.asarray(layout.tray_rgb, np.float32) * (1.0 + 2 * redder * tint)
    albedo = (phantom_rgb * on_phantom + tray_rgb * (1 - on_phantom)) * shade
    darken = np.asarray(layout.vessel_rgb, np.float32)  # albedo factor at a vessel's core
    albedo *= 1.0 - (1.0 - darken) * (0.85 * vessels)[..., None]
    wet = np.clip(0.6 + 0.35 * _value_noise(rng, shape, 0.004 / texel_m), 0.05, 1.0).astype(np.float32)
    bump = _value_noise(rng, shape, _BUMP_CELL_M / texel_m)
    slopes = np.stack(np.gradient(bump, texel_m)[::-1], axis=-1)
    slopes *= _BUMP_SLOPE / max(float(slopes.std()), 1e-9)
    return np.clip(albedo, 0.0, 1.0).astype(np.float32), wet, slopes.astype(np.float32)


class Renderer:
    """Ray casts and shades the stereo pair of one frame; built once per session.

    Shading: each view is lit by a point light at its own centre (the endoscope's light guide),
    so light, view and half vectors coincide: radiance = (albedo (n.v) + broad + sharp specular)
    x (d0 / distance)^2 x vignetting, then a soft tone curve and gamma 2.
    """

    def __init__(self, params: SynthParams, camera: StereoCamera, frame: TissueFrame, rng: np.random.Generator):
        import open3d as o3d  # this module's job needs it; imported lazily to keep import cheap

        self.o3d = o3d
        self.params, self.camera, self.frame = params, camera, frame
        phantom = params.phantom
        h, w = camera.height, camera.width
        px_per_m = camera.fx / params.tissue_distance_m

        # Tissue grid (phantom units, TissueFrame): covers the base-plane footprint of both views' corners,
        # with margin. Mesh cells and texels are sized in camera-frame metres, then turned into phantom units:
        # the texture scales with the phantom.
        corners = camera.pixel_rays(np.array([0, w - 1]), np.array([0, h - 1])).reshape(-1, 3).astype(np.float64)
        uv = []
        for origin in (np.zeros(3), np.array([camera.baseline_m, 0, 0])):
            t = ((frame.origin_m - origin) @ frame.normal) / (corners @ frame.normal)
            pu, pv, _ = frame.to_tissue(origin + t[:, None] * corners)
            uv.append(np.stack([pu, pv], 1))
        uv = np.concatenate(uv)
        margin = 0.012  # phantom units
        (u0, v0), (u1, v1) = uv.min(0) - margin, uv.max(0) + margin
        cell = min(params.mesh_cell_px / px_per_m, _MAX_CELL_M) / frame.scale
        nu, nv = int(math.ceil((u1 - u0) / cell)) + 1, int(math.ceil((v1 - v0) / cell)) + 1
        self.u_grid, self.v_grid = np.linspace(u0, u1, nu), np.linspace(v0, v1, nv)
        self.nu, self.nv = nu, nv
        self.rest = surface_points(phantom, frame, self.u_grid[None, :], self.v_grid[:, None]).reshape(-1, 3)
        idx = np.arange(nu * nv, dtype=np.int64).reshape(nv, nu)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
        self.triangles = np.stack([np.stack([a, b, c], 1), np.stack([d, c, b], 1)], 1).reshape(-1, 3).astype(np.uint32)

        # Surface maps over the same (u, v) rectangle.
        texel = _TEXEL_PX / px_per_m / frame.scale
        tw = min(_MAX_TEXTURE_PX, int(math.ceil((u1 - u0) / texel)) + 1)
        th = min(_MAX_TEXTURE_PX, int(math.ceil((v1 - v0) / texel)) + 1)
        albedo, wet, slopes = _tissue_texture(phantom, np.linspace(u0, u1, tw), np.linspace(v0, v1, th), rng)
        # Material maps: albedo BGR; broad and sharp specular weights; bump offsets of the normal (3D).
        self.albedo = np.ascontiguousarray(albedo[..., ::-1])
        self.specular = np.dstack([wet * _TISSUE.gloss, wet * _TISSUE.shine]).astype(np.float32)
        self.bump = (-(slopes[..., :1] * frame.e_u) - slopes[..., 1:] * frame.e_v).astype(np.float32)
        self.tex_scale = ((tw - 1) / (nu - 1), (th - 1) / (nv - 1))

        # Unit primitives for the tool.
        angles = np.linspace(0, 2 * np.pi, _CYL_SEGMENTS, endpoint=False)
        ring = np.stack([np.cos(angles), np.sin(angles)], 1)
        m = _CYL_SEGMENTS
        self.cyl_vertices = np.concatenate([np.c_[ring, np.zeros(m)], np.c_[ring, np.ones(m)], [[0, 0, 0], [0, 0, 1]]])
        k = np.arange(m)
        k1 = (k + 1) % m
        self.cyl_triangles = np.concatenate(
            [
                np.c_[k, k1, k + m],
                np.c_[k1, k1 + m, k + m],
                np.c_[np.full(m, 2 * m), k1, k],
                np.c_[np.full(m, 2 * m + 1), k + m, k1 + m],
            ]
        ).astype(np.uint32)
        sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=_SPHERE_RES)
        self.sphere_vertices = np.asarray(sphere.vertices, dtype=np.float64)
        self.sphere_triangles = np.asarray(sphere.triangles, dtype=np.uint32)

        # Rays, per-pixel view vectors and the coarse lattice of the adaptive tracer.
        self.dirs = camera.pixel_rays(np.arange(w), np.arange(h))
        inv_len = 1.0 / np.linalg.norm(self.dirs, axis=-1)
        self.to_eye = (-self.dirs * inv_len[..., None]).astype(np.float32)
        r2 = self.dirs[..., 0] ** 2 + self.dirs[..., 1] ** 2
        vignette = (1.0 + _VIGNETTE * r2) ** -2
        # Irradiance factor without the depth: (d0 / (z |dir|))^2 x vignetting = light_gain / z^2.
        self._rest_cache = None  # (scene, normal grid) of the undeformed tissue, built on first use
        self._ray_cache: dict = {}  # ray tensors of the full pixel grid / lattice, per view
        self.light_gain = (params.tissue_distance_m**2 * inv_len**2 * vignette * _EXPOSURE).astype(np.float32)
        # The lattice keeps its angular size: coarser images get a finer step (320 px wide: one ray per pixel).
        self.step = max(1, round(params.raycast_step_px * w / REFERENCE_WIDTH_PX))
        if self.step > 1:
            s = self.step
            ny, nx = (h - 1) // s + 2, (w - 1) // s + 2
            self.coarse_dirs = camera.pixel_rays(np.arange(nx) * s, np.arange(ny) * s)
            map_x = np.broadcast_to(np.arange(w, dtype=np.float32)[None, :] / s, (h, w))
            map_y = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None] / s, (h, w))
            self.coarse_maps = cv2.convertMaps(np.ascontiguousarray(map_x), np.ascontiguousarray(map_y), cv2.CV_16SC2)

    # -- scene --------------------------------------------------------------------------------
    def _tissue_scene(self, vertices: np.ndarray):
        """Ray casting scene of the tissue mesh with these vertices (N, 3), m."""
        o3d = self.o3d
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(self.triangles))
        return scene

    def _tool_scene(self, parts: list[_Part]):
        """Ray casting scene of the tool; geometry k is parts[k]."""
        o3d = self.o3d
        scene = o3d.t.geometry.RaycastingScene()
        for part in parts:
            if part.kind == "cylinder":
                axis = part.b - part.a
                length = float(np.linalg.norm(axis))
                z = axis / length
                x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
                x /= np.linalg.norm(x)
                y = np.cross(z, x)
                local = self.cyl_vertices * np.array([part.radius, part.radius, length])
                verts = part.a + local @ np.stack([x, y, z])
                tris = self.cyl_triangles
            else:
                verts = part.a + self.sphere_vertices * part.radius
                tris = self.sphere_triangles
            scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris))
        return scene

    def _rays(self, origin: np.ndarray, dirs: np.ndarray, cache_key: str | None = None):
        """open3d ray tensor (M, 6) from one origin along dirs (M, 3); cached per (view, lattice)."""
        key = (cache_key, float(origin[0]))
        if cache_key is not None and key in self._ray_cache:
            return self._ray_cache[key]
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs
        tensor = self.o3d.core.Tensor.from_numpy(rays)
        if cache_key is not None:
            self._ray_cache[key] = (tensor, rays)  # keep the numpy buffer alive with its view
            return self._ray_cache[key]
        return tensor, rays

    def _cast(self, scenes, origin: np.ndarray, dirs: np.ndarray, cache_key: str | None = None):
        """Cast rays (M, 3) from origin into the (tissue, tool) scenes.

        Returns z-depth (M,) (inf = miss), geometry id (M,) (-1 miss, 0 tissue, k + 1 tool part k)
        and the tissue grid coordinates (i, j) of each hit (0 off the tissue).
        """
        tissue_scene, tool_scene = scenes
        rays_t, _ = self._rays(origin, dirs, cache_key)
        out = tissue_scene.cast_rays(rays_t)
        t = out["t_hit"].numpy()
        tool = tool_scene.cast_rays(rays_t)
        t_tool = tool["t_hit"].numpy()
        on_tool = t_tool < t
        gid = np.where(np.isfinite(t), 0, -1)
        gid[on_tool] = tool["geometry_ids"].numpy()[on_tool].astype(np.int64) + 1
        t = np.where(on_tool, t_tool, t)
        gi = np.zeros(len(t), np.float32)
        gj = np.zeros(len(t), np.float32)
        tissue = np.flatnonzero(gid == 0)
        # Grid triangles 2k and 2k+1 split cell k = (ci, cj); see the triangle list in __init__.
        prim = out["primitive_ids"].numpy()[tissue].astype(np.int32)
        bary = out["primitive_uvs"].numpy()[tissue]
        cell, second = prim // 2, (prim % 2) == 1
        ci, cj = cell // (self.nu - 1), cell % (self.nu - 1)
        gi[tissue] = np.where(second, ci + 1 - bary[:, 0], ci + bary[:, 0])
        gj[tissue] = np.where(second, cj + 1 - bary[:, 1], cj + bary[:, 1])
        return t, gid, gi, gj

    def _trace(self, scenes, origin: np.ndarray):
        """Per-pixel z-depth (H, W) float32 (0 = miss), geometry id (H, W) int64, grid coordinates.

        Adaptive: rays on a lattice every ``raycast_step_px`` px; a lattice cell whose four corners hit
        the same geometry at nearly the same inverse depth is filled by bilinear interpolation of
        inverse depth (exact on planes) and grid coordinates; every other pixel gets its own ray.
        """
        h, w = self.camera.height, self.camera.width
        if self.step == 1:
            t, gid, gi, gj = self._cast(scenes, origin, self.dirs.reshape(-1, 3), "full")
            z = np.where(np.isfinite(t), t, 0).astype(np.float32)
            return z.reshape(h, w), gid.reshape(h, w), gi.reshape(h, w), gj.reshape(h, w)
        s = self.step
        ny, nx = self.coarse_dirs.shape[:2]
        t, gid, gi, gj = self._cast(scenes, origin, self.coarse_dirs.reshape(-1, 3), "lattice")
        inv = np.where(np.isfinite(t), 1.0 / t, 0).astype(np.float32).reshape(ny, nx)
        g, gi, gj = gid.reshape(ny, nx), gi.reshape(ny, nx), gj.reshape(ny, nx)
        c00, c10, c01, c11 = g[:-1, :-1], g[1:, :-1], g[:-1, 1:], g[1:, 1:]
        same = (c00 == c10) & (c00 == c01) & (c00 == c11)
        i4 = np.stack([inv[:-1, :-1], inv[1:, :-1], inv[:-1, 1:], inv[1:, 1:]])
        # Inverse depth is linear in the image on a plane; a cell's relative spread above what a surface
        # at slope _GRAZING_SLOPE gives over the cell's width marks a depth edge (self-occlusion).
        tol = _GRAZING_SLOPE * s / self.camera.fx
        smooth = (i4.max(0) - i4.min(0)) <= tol * i4.max(0)
        # Trace cells next to a traced cell too: catches thin protrusions (a jaw tip) between lattice rays.
        ok = cv2.erode((same & smooth).astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
        ok_px = np.repeat(np.repeat(ok, s, 0), s, 1)[:h, :w]
        gid_px = np.repeat(np.repeat(c00, s, 0), s, 1)[:h, :w].copy()
        map1, map2 = self.coarse_maps
        inv_px = cv2.remap(inv, map1, map2, cv2.INTER_LINEAR)
        gi_px = cv2.remap(gi, map1, map2, cv2.INTER_LINEAR)
        gj_px = cv2.remap(gj, map1, map2, cv2.INTER_LINEAR)
        bad = np.flatnonzero(~ok_px)
        if len(bad):
            tb, gb, gib, gjb = self._cast(scenes, origin, self.dirs.reshape(-1, 3)[bad])
            inv_px.reshape(-1)[bad] = np.where(np.isfinite(tb), 1.0 / tb, 0)
            gid_px.reshape(-1)[bad] = gb
            gi_px.reshape(-1)[bad] = gib
            gj_px.reshape(-1)[bad] = gjb
        hit = (gid_px >= 0) & (inv_px > 0)
        z = np.zeros((h, w), np.float32)
        np.divide(1.0, inv_px, out=z, where=hit)
        gid_px[~hit] = -1
        return z, gid_px, gi_px, gj_px

    # -- shading --------------------------------------------------------------------------------
    def _shade(self, origin, z, gid, gi, gj, normal_grid, parts):
        """BGR uint8 image (H, W, 3) and sharp specular radiance (H, W) float32 of one view."""
        grid_maps = cv2.convertMaps(gj, gi, cv2.CV_16SC2)
        tex_maps = cv2.convertMaps(gj * np.float32(self.tex_scale[0]), gi * np.float32(self.tex_scale[1]), cv2.CV_16SC2)
        normals = cv2.add(
            cv2.remap(normal_grid, *grid_maps, cv2.INTER_LINEAR), cv2.remap(self.bump, *tex_maps, cv2.INTER_LINEAR)
        )
        albedo = cv2.remap(self.albedo, *tex_maps, cv2.INTER_LINEAR)
        weights = cv2.remap(self.specular, *tex_maps, cv2.INTER_LINEAR)  # broad, sharp
        channel_sum = np.ones((1, 3), np.float32)
        cos_v = cv2.transform(cv2.multiply(normals, self.to_eye), channel_sum)
        length = cv2.sqrt(cv2.transform(cv2.multiply(normals, normals), channel_sum))
        cos_v = np.abs(cv2.divide(cos_v, length))  # two-sided
        broad = cos_v.copy()
        for _ in range(_TISSUE.gloss_squarings):
            broad *= broad
        sharp = broad.copy()
        for _ in range(_TISSUE.shine_squarings - _TISSUE.gloss_squarings):
            sharp *= sharp
        broad *= weights[..., 0]
        sharp *= weights[..., 1]

        # Tool pixels: analytic normals of the primitives, tool materials.
        tool_px = np.flatnonzero(gid > 0)
        tool_gid = gid.reshape(-1)[tool_px]
        flat_dirs, flat_eye = self.dirs.reshape(-1, 3), self.to_eye.reshape(-1, 3)
        for k, part in enumerate(parts):
            sel = tool_px[tool_gid == k + 1]
            if not len(sel):
                continue
            p = origin + flat_dirs[sel].astype(np.float64) * z.reshape(-1)[sel, None]
            if part.kind == "cylinder":
                d = part.b - part.a
                length = np.linalg.norm(d)
                d = d / length
                rel = p - part.a
                along = rel @ d
                radial = rel - along[:, None] * d
                rad = np.linalg.norm(radial, axis=1)
                nrm = radial / np.maximum(rad, 1e-9)[:, None]
                cap = rad < 0.97 * part.radius
                nrm[cap] = np.where((along[cap] < length / 2)[:, None], -d, d)
            else:
                nrm = (p - part.a) / np.linalg.norm(p - part.a, axis=1, keepdims=True)
            mat = _TOOL_MATERIALS[part.material]
            c = np.abs(np.sum(nrm * flat_eye[sel], axis=1)).astype(np.float32)
            cos_v.reshape(-1)[sel] = c
            broad.reshape(-1)[sel] = mat.gloss * c ** (2**mat.gloss_squarings)
            sharp.reshape(-1)[sel] = mat.shine * c ** (2**mat.shine_squarings)
            albedo.reshape(-1, 3)[sel] = mat.albedo[::-1]

        light = np.zeros_like(z)
        np.divide(self.light_gain, cv2.multiply(z, z), out=light, where=z > 0)  # 0 where nothing is hit
        sharp *= light
        diffuse = (cos_v + _AMBIENT) * light
        glints = (broad * cos_v) * light + sharp
        linear = cv2.add(cv2.multiply(albedo, cv2.merge([diffuse] * 3)), cv2.merge([glints] * 3))
        # Soft shoulder y = (1 + s) x / (1 + s x) (maps 1 to 1), then gamma 2 and 8 bits (saturating).
        toned = cv2.divide(linear, cv2.addWeighted(linear, _SHOULDER, linear, 0.0, 1.0), scale=1.0 + _SHOULDER)
        bgr = cv2.convertScaleAbs(cv2.sqrt(toned), alpha=255.0)
        return bgr, sharp

    def _normal_grid(self, vertices: np.ndarray) -> np.ndarray:
        """Unit vertex normals (nv, nu, 3) float32 of the tissue grid, pointing out of the tissue."""
        grid = vertices.reshape(self.nv, self.nu, 3)
        normal_grid = np.cross(np.gradient(grid, axis=0), np.gradient(grid, axis=1))
        normal_grid /= np.linalg.norm(normal_grid, axis=-1, keepdims=True)
        return normal_grid.astype(np.float32)

    def render(self, displacement: np.ndarray | None, parts: list[_Part],
               part_tools: list[int] | None = None) -> dict[str, dict[str, np.ndarray]]:
        """Both views of one frame: BGR uint8 image, z-depth (0 = miss), tool mask, tool id, specular radiance.

        ``displacement`` (N, 3) moves the tissue vertices ``rest`` (m); None = undeformed, which
        reuses a cached scene (building the acceleration structure is a large part of a frame).
        ``parts`` are the primitives of every tool; ``part_tools`` gives each one's tool id (1, 2, ...;
        default all 1). ``tool_id`` (H, W) uint8 is the id of the nearest tool seen at each pixel, 0 = none.
        """
        if displacement is None:
            if self._rest_cache is None:
                self._rest_cache = (self._tissue_scene(self.rest), self._normal_grid(self.rest))
            tissue_scene, normal_grid = self._rest_cache
        else:
            vertices = self.rest + displacement
            tissue_scene, normal_grid = self._tissue_scene(vertices), self._normal_grid(vertices)
        scenes = (tissue_scene, self._tool_scene(parts))
        lookup = np.zeros(len(parts) + 2, np.uint8)  # by geometry id + 1: miss, tissue, part 0, part 1, ...
        lookup[2:] = 1 if part_tools is None else part_tools
        views = {}
        for name, origin in (("left", np.zeros(3)), ("right", np.array([self.camera.baseline_m, 0.0, 0.0]))):
            z, gid, gi, gj = self._trace(scenes, origin)
            bgr, specular = self._shade(origin, z, gid, gi, gj, normal_grid, parts)
            views[name] = {"image": bgr, "z": z, "tool": gid > 0, "tool_id": lookup[gid + 1], "specular": specular}
        return views
