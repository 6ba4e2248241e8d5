"""Which renderer should make the virtual objects' camera G-buffer: a measurement.

Two renderers of the same `VirtualGBuffer` (depth along the optical axis, camera-frame
two-sided interpolated normals, albedo, object index; see pipeline/virtual_gbuffer.py):

  open3d    `VirtualRaycaster.camera_gbuffer`: Open3D `RaycastingScene` (Embree, CPU), rays
            only through the pixels inside the objects' `screen_rect`;
  moderngl  `GLGBufferRenderer.camera_gbuffer` (here): OpenGL 3.3 core over EGL, headless,
            rasterised into an offscreen framebuffer (RGBA32F camera normal + linear depth,
            R8 object index + 1, a depth buffer for the depth test), then read back into
            numpy and turned into a `VirtualGBuffer`. On a machine without a GPU, Mesa's
            EGL gives llvmpipe (software rasteriser on the CPU); on a GPU machine, the GPU.

For every --triangles count a scene is built of a UV sphere (its subdivision chosen so that
sphere + torus have about that many triangles) and a torus, standing 0.6-0.7 m in front of
a Kinect-like PinholeCamera (arlight/core/camera.py, scaled to each --sizes); every frame the
camera pose moves a little (a few millimetres and tenths of a degree) so that nothing can be
cached between frames. Per configuration it prints the median milliseconds per frame over
--frames frames (after --warmup frames, not counted) of each renderer, moderngl's time split
into draw (up to glFinish) and read-back + conversion to the VirtualGBuffer, and the time of
the first frame (which pays Open3D's lazy BVH build and Mesa's shader compilation). One-time
costs are printed apart: creating the EGL context, building the Open3D scene, compiling the
GL program, uploading the meshes, making the framebuffer.

Agreement (on one pose per configuration), so that a wrong projection shows: IoU of the two
hit masks, median |depth difference| (mm) and median angle between the normals (degrees)
over the pixels both hit, and the fraction of those with the same object index.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/gbuffer_renderers.py \\
        [--sizes 320x240 640x480 1280x720] [--triangles 5000 100000 1000000] \\
        [--frames 20] [--warmup 3] [--out FILE.json]

moderngl: `.venv/bin/python -m pip install moderngl` (with glcontext) and an EGL with a
GL driver (Debian: `apt-get install libegl1 libgl1-mesa-dri`). Without them the script says
so in one line and measures the Open3D column alone.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.pipeline.virtual_gbuffer import NEAR_M, VirtualGBuffer, VirtualRaycaster
from arlight.pipeline.virtual_scene import (
    Material,
    VirtualScene,
    object_from_open3d,
    sphere_mesh,
    torus_mesh,
)

FAR_M = 100.0  # the GL far plane; the depth test needs one, the scene is well inside it
TORUS_RESOLUTION = 40  # 1600 triangles
INSTALL_HINT = (
    "moderngl over EGL is not available ({error}); install it with "
    "`.venv/bin/python -m pip install moderngl` (and, on Debian, "
    "`apt-get install libegl1 libgl1-mesa-dri`); measuring Open3D alone"
)

_VERTEX = """
#version 330
uniform mat4 cam_from_world;
uniform vec4 clip_xy;  // (2 fx / W, 2 (cx + 0.5) / W - 1, 2 fy / H, 2 (cy + 0.5) / H - 1)
uniform vec2 clip_z;   // z_clip = clip_z.x * z + clip_z.y (near -> -1, far -> +1 after / z)
in vec3 in_position;   // world frame
in vec3 in_normal;     // world frame
out vec3 v_position;   // camera frame (OpenCV: x right, y down, z forward)
out vec3 v_normal;
void main() {
    vec4 p = cam_from_world * vec4(in_position, 1.0);
    v_position = p.xyz;
    v_normal = mat3(cam_from_world) * in_normal;  // rigid: the rotation maps normals
    // pixel (u, v) = (fx x / z + cx, fy y / z + cy), pixel centres at integers; GL's window
    // coordinate of that centre is u + 0.5. y is NOT flipped: GL's row 0 (bottom) is image
    // row v = 0, so the framebuffer reads back in image order, top row first.
    gl_Position = vec4(clip_xy.x * p.x + clip_xy.y * p.z, clip_xy.z * p.y + clip_xy.w * p.z,
                       clip_z.x * p.z + clip_z.y, p.z);
}
"""

_FRAGMENT = """
#version 330
uniform float object_code;  // (object index + 1) / 255
in vec3 v_position;
in vec3 v_normal;
layout(location = 0) out vec4 out_normal_depth;
layout(location = 1) out float out_object;
void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, v_position) > 0.0) n = -n;  // two-sided: the side the camera sees
    out_normal_depth = vec4(n, v_position.z);  // perspective-correct: the plane's z
    out_object = object_code;
}
"""


class GLGBufferRenderer:
    """The camera G-buffer of a virtual scene by rasterising it with moderngl.

    The meshes are uploaded once (world frame); `camera_gbuffer` has the interface and the
    result of `VirtualRaycaster.camera_gbuffer`, except that depth_m and normals_cam are views
    into one (H, W, 4) float32 array (read back in one call). At most 254 objects."""

    def __init__(self, scene: VirtualScene, ctx):
        self.ctx = ctx
        self.program = ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        self._objects = []  # (vao, vbo, ibo, object_code)
        for index, obj in enumerate(scene.objects):
            data = np.hstack([obj.world_vertices(), obj.world_normals()]).astype(np.float32)
            vbo = ctx.buffer(data.tobytes())
            ibo = ctx.buffer(obj.triangles.astype(np.uint32).tobytes())
            vao = ctx.vertex_array(
                self.program,
                [(vbo, "3f 3f", "in_position", "in_normal")],
                index_buffer=ibo,
                index_element_size=4,
            )
            self._objects.append((vao, vbo, ibo, (index + 1) / 255.0))
        # index 0: no object
        self._albedo = np.zeros((256, 3), np.float32)
        for index, obj in enumerate(scene.objects):
            self._albedo[index + 1] = obj.material.albedo
        self._fbo = None
        self._size = None

    def _framebuffer(self, width: int, height: int):
        if self._size != (width, height):
            self.release_framebuffer()
            normal_depth = self.ctx.texture((width, height), 4, dtype="f4")
            objects = self.ctx.texture((width, height), 1, dtype="f1")
            depth = self.ctx.depth_texture((width, height))
            self._fbo = self.ctx.framebuffer([normal_depth, objects], depth)
            self._size = (width, height)
        return self._fbo

    def release_framebuffer(self) -> None:
        if self._fbo is not None:
            for attachment in (*self._fbo.color_attachments, self._fbo.depth_attachment):
                attachment.release()
            self._fbo.release()
            self._fbo, self._size = None, None

    def release(self) -> None:
        self.release_framebuffer()
        for vao, vbo, ibo, _ in self._objects:
            vao.release()
            vbo.release()
            ibo.release()
        self.program.release()

    def draw(self, camera: PinholeCamera, world_from_cam: np.ndarray) -> None:
        """Rasterise the scene into the framebuffer (asynchronously: see `read`)."""
        import moderngl

        w, h = camera.width, camera.height
        fbo = self._framebuffer(w, h)
        fbo.use()
        fbo.viewport = (0, 0, w, h)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        cam_from_world = np.linalg.inv(world_from_cam)
        # GLSL matrices are column-major: the transpose's bytes in C order
        self.program["cam_from_world"].write(cam_from_world.T.astype(np.float32).tobytes())
        self.program["clip_xy"].value = (
            2.0 * camera.fx / w,
            2.0 * (camera.cx + 0.5) / w - 1.0,
            2.0 * camera.fy / h,
            2.0 * (camera.cy + 0.5) / h - 1.0,
        )
        self.program["clip_z"].value = (
            (FAR_M + NEAR_M) / (FAR_M - NEAR_M),
            -2.0 * FAR_M * NEAR_M / (FAR_M - NEAR_M),
        )
        for vao, _, _, code in self._objects:
            self.program["object_code"].value = code
            vao.render()

    def read(self) -> VirtualGBuffer:
        """The last drawn frame, read back into numpy (waits for the draw)."""
        w, h = self._size
        normal_depth = np.empty((h, w, 4), np.float32)
        codes = np.empty((h, w), np.uint8)
        self._fbo.color_attachments[0].read_into(normal_depth)
        self._fbo.color_attachments[1].read_into(codes)
        return VirtualGBuffer(
            depth_m=normal_depth[..., 3],
            normals_cam=normal_depth[..., :3],
            albedo=self._albedo[codes],
            object_index=codes.astype(np.int32) - 1,
        )

    def camera_gbuffer(self, camera: PinholeCamera, world_from_cam: np.ndarray) -> VirtualGBuffer:
        self.draw(camera, world_from_cam)
        return self.read()


def gl_context():
    """(moderngl context, None) or (None, why not)."""
    try:
        import moderngl
    except ImportError as exc:
        return None, f"import moderngl: {exc}"
    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as exc:  # glcontext raises plain Exceptions naming the EGL call
        return None, f"EGL context: {type(exc).__name__}: {exc}"
    if ctx.version_code < 330:
        ctx.release()
        return None, f"OpenGL {ctx.version_code} < 3.3"
    return ctx, None


def sphere_resolution(triangles: int) -> int:
    """The UV-sphere resolution whose 4 r (r - 1) triangles plus the torus's come nearest
    to `triangles`."""
    want = max(triangles - 2 * TORUS_RESOLUTION * (TORUS_RESOLUTION // 2), 24)
    return max(3, int(round((1.0 + np.sqrt(1.0 + want)) / 2.0)))


def bench_scene(triangles: int, with_torus: bool = True) -> VirtualScene:
    """A grey sphere (radius 0.12 m) and an upright orange torus standing in front of a
    camera at the world origin looking along +z (world = camera frame of the first pose)."""
    # object +y up -> camera -y (up in the image); object +z -> towards the camera
    upright = np.diag([1.0, -1.0, -1.0, 1.0])
    pose = upright.copy()
    pose[:3, 3] = (-0.12, 0.12, 0.7)
    objects = [
        object_from_open3d(
            "sphere",
            sphere_mesh(0.12, sphere_resolution(triangles)),
            pose,
            Material((0.6, 0.6, 0.6)),
        )
    ]
    if with_torus:
        turn = np.radians(30.0)
        yaw = np.eye(4)
        yaw[[0, 0, 2, 2], [0, 2, 0, 2]] = np.cos(turn), np.sin(turn), -np.sin(turn), np.cos(turn)
        pose = upright @ yaw
        pose[:3, 3] = (0.14, 0.12, 0.6)
        objects.append(
            object_from_open3d(
                "torus", torus_mesh(0.1, 0.035, TORUS_RESOLUTION), pose, Material((0.8, 0.3, 0.08))
            )
        )
    return VirtualScene(tuple(objects))


def camera_pose(frame: int) -> np.ndarray:
    """world_from_cam of frame `frame`: a few mm and a few tenths of a degree off identity."""
    a = np.radians(0.4) * np.sin(0.9 * frame + 0.3)
    b = np.radians(0.3) * np.cos(0.7 * frame)
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    yaw = np.array([[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]])
    pitch = np.array([[1.0, 0.0, 0.0], [0.0, cb, -sb], [0.0, sb, cb]])
    m = np.eye(4)
    m[:3, :3] = yaw @ pitch
    m[:3, 3] = 0.004 * np.array([np.sin(1.3 * frame), np.cos(1.1 * frame), np.sin(0.5 * frame)])
    return m


def agreement(a: VirtualGBuffer, b: VirtualGBuffer) -> dict:
    """IoU of the hit masks; over the pixels both hit: median and 99th percentile of
    |depth a - depth b| (mm), median angle between the normals (degrees), the fraction with
    the same object index."""
    ha, hb = a.hit, b.hit
    union = int(np.count_nonzero(ha | hb))
    both = ha & hb
    out = {
        "iou": float(np.count_nonzero(both) / union) if union else 1.0,
        "pixels_hit": [int(np.count_nonzero(ha)), int(np.count_nonzero(hb))],
    }
    if not both.any():
        return {
            **out,
            "depth_mm_median": None,
            "depth_mm_p99": None,
            "normal_deg_median": None,
            "same_object": None,
        }
    dd = np.abs(a.depth_m[both].astype(np.float64) - b.depth_m[both]) * 1000.0
    cos = np.clip(
        np.einsum("ij,ij->i", a.normals_cam[both].astype(np.float64), b.normals_cam[both]),
        -1.0,
        1.0,
    )
    return {
        **out,
        "depth_mm_median": float(np.median(dd)),
        "depth_mm_p99": float(np.percentile(dd, 99)),
        "normal_deg_median": float(np.degrees(np.median(np.arccos(cos)))),
        "same_object": float(np.mean(a.object_index[both] == b.object_index[both])),
    }


def _ms(seconds: float) -> float:
    return round(seconds * 1000.0, 3)


def time_frames(render, camera: PinholeCamera, frames: int, warmup: int, start: int) -> dict:
    """First-frame and median per-frame milliseconds of render(camera, pose) -> splits."""
    first = time.perf_counter()
    render(camera, camera_pose(start))
    first = time.perf_counter() - first
    for i in range(1, warmup):
        render(camera, camera_pose(start + i))
    totals, parts = [], []
    for i in range(frames):
        t0 = time.perf_counter()
        split = render(camera, camera_pose(start + warmup + i))
        totals.append(time.perf_counter() - t0)
        parts.append(split)
    out = {"first_frame_ms": _ms(first), "ms": _ms(float(np.median(totals)))}
    if parts and parts[0] is not None:
        for key in parts[0]:
            out[f"{key}_ms"] = _ms(float(np.median([p[key] for p in parts])))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sizes",
        nargs="+",
        default=["320x240", "640x480", "1280x720"],
        help="camera image sizes WIDTHxHEIGHT",
    )
    parser.add_argument(
        "--triangles",
        nargs="+",
        type=int,
        default=[5000, 100000, 1000000],
        help="about this many triangles in the scene (sphere + torus)",
    )
    parser.add_argument("--frames", type=int, default=20, help="timed frames per config")
    parser.add_argument("--warmup", type=int, default=3, help="untimed frames first (>= 1)")
    parser.add_argument("--out", type=Path, help="also write the figures here (JSON)")
    args = parser.parse_args(argv)
    sizes = []
    for text in args.sizes:
        try:
            w, h = (int(x) for x in text.lower().split("x"))
        except ValueError:
            parser.error(f"--sizes: {text!r} is not WIDTHxHEIGHT")
        sizes.append((w, h))
    if args.frames < 1 or args.warmup < 1:
        parser.error("--frames and --warmup must be >= 1")

    t0 = time.perf_counter()
    ctx, why = gl_context()
    context_s = time.perf_counter() - t0
    gl_info = {}
    if ctx is None:
        print(INSTALL_HINT.format(error=why))
    else:
        gl_info = {k: ctx.info[k] for k in ("GL_VENDOR", "GL_RENDERER", "GL_VERSION")}
        print(
            f"moderngl {sys.modules['moderngl'].__version__} over EGL: "
            f"{gl_info['GL_RENDERER']} ({gl_info['GL_VERSION']}); "
            f"context created in {_ms(context_s)} ms"
        )

    setups, rows = [], []
    for target in args.triangles:
        t0 = time.perf_counter()
        scene = bench_scene(target)
        build_s = time.perf_counter() - t0
        n_tri = sum(len(o.triangles) for o in scene.objects)
        t0 = time.perf_counter()
        raycaster = VirtualRaycaster(scene)
        o3d_s = time.perf_counter() - t0
        setup = {
            "triangles_target": target,
            "triangles": n_tri,
            "scene_build_ms": _ms(build_s),
            "open3d_setup_ms": _ms(o3d_s),
        }
        gl = None
        if ctx is not None:
            t0 = time.perf_counter()
            gl = GLGBufferRenderer(scene, ctx)
            ctx.finish()
            setup["moderngl_setup_ms"] = _ms(time.perf_counter() - t0)
        setups.append(setup)

        for k, (w, h) in enumerate(sizes):
            camera = PinholeCamera.kinect_v1(w, h)
            row = {"size": f"{w}x{h}", "triangles": n_tri}

            def o3d_render(cam, pose, rc=raycaster):
                rc.camera_gbuffer(cam, pose)

            row["open3d"] = time_frames(o3d_render, camera, args.frames, args.warmup, 100 * k)
            if gl is not None:
                t0 = time.perf_counter()
                gl._framebuffer(w, h)
                ctx.finish()
                fbo_s = time.perf_counter() - t0

                def gl_render(cam, pose, r=gl):
                    t0 = time.perf_counter()
                    r.draw(cam, pose)
                    r.ctx.finish()
                    t1 = time.perf_counter()
                    r.read()
                    return {"draw": t1 - t0, "read": time.perf_counter() - t1}

                row["moderngl"] = time_frames(gl_render, camera, args.frames, args.warmup, 100 * k)
                row["moderngl"]["framebuffer_ms"] = _ms(fbo_s)
                pose = camera_pose(7)
                row["agreement"] = agreement(
                    raycaster.camera_gbuffer(camera, pose), gl.camera_gbuffer(camera, pose)
                )
            rows.append(row)
            print(
                f"  {n_tri} triangles {w}x{h}: open3d {row['open3d']['ms']} ms"
                + (f", moderngl {row['moderngl']['ms']} ms" if gl is not None else ""),
                flush=True,
            )
        if gl is not None:
            gl.release()

    print()
    print(
        f"Per frame, median of {args.frames} (after {args.warmup} warm-up), milliseconds; "
        f"{os.cpu_count()} CPU cores" + (f"; GL: {gl_info['GL_RENDERER']}" if gl_info else "")
    )
    print()
    print(
        "| size | triangles | Open3D ms | moderngl ms (draw + read) | Open3D / moderngl "
        "| first frame ms O3D / GL | mask IoU | depth mm median (p99) | normal deg median "
        "| same object |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        o = r["open3d"]
        if "moderngl" in r:
            g, a = r["moderngl"], r["agreement"]

            def f(x, digits=3):
                return "-" if x is None else f"{x:.{digits}f}"

            gl_cols = (
                f"{g['ms']:.2f} ({g['draw_ms']:.2f} + {g['read_ms']:.2f}) | "
                f"{o['ms'] / g['ms']:.2f} | {o['first_frame_ms']:.0f} / "
                f"{g['first_frame_ms']:.0f} | {a['iou']:.4f} | {f(a['depth_mm_median'])} "
                f"({f(a['depth_mm_p99'])}) | {f(a['normal_deg_median'])} | "
                f"{f(a['same_object'], 4)}"
            )
        else:
            gl_cols = f"- | - | {o['first_frame_ms']:.0f} / - | - | - | - | -"
        print(f"| {r['size']} | {r['triangles']} | {o['ms']:.2f} | {gl_cols} |")
    print()
    print(
        "One-time costs, milliseconds"
        + (f" (EGL context creation: {_ms(context_s)})" if ctx is not None else "")
    )
    print()
    print(
        "| triangles | scene build | Open3D RaycastingScene | moderngl program + upload |"
        + " moderngl framebuffer per size |"
    )
    print("|---:|---:|---:|---:|---|")
    for s in setups:
        fbos = (
            ", ".join(
                f"{r['size']}: {r['moderngl']['framebuffer_ms']:.1f}"
                for r in rows
                if r["triangles"] == s["triangles"] and "moderngl" in r
            )
            or "-"
        )
        gl_setup = f"{s['moderngl_setup_ms']:.1f}" if "moderngl_setup_ms" in s else "-"
        print(
            f"| {s['triangles']} | {s['scene_build_ms']:.1f} | {s['open3d_setup_ms']:.1f} | "
            f"{gl_setup} | {fbos} |"
        )
    print(
        "(Open3D builds its BVH on the first cast and Mesa compiles shaders on the first "
        "draw: both are in the first-frame column.)"
    )

    if args.out:
        report = {
            "frames": args.frames,
            "warmup": args.warmup,
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "env": {k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "LP_NUM_THREADS")},
            "moderngl": gl_info or {"unavailable": why},
            "egl_context_ms": _ms(context_s) if ctx is not None else None,
            "setup": setups,
            "results": rows,
        }
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=2))
        print(f"wrote {args.out}")
    if ctx is not None:
        ctx.release()
    return 0


if __name__ == "__main__":
    sys.exit(main())
