"""Virtual-scene files: the objects to render into the camera image (docs/scene-files.md).

One loader, two layouts:
- ours, ``{"objects": [...]}``: each object a mesh file or a built-in primitive, a pose or an
  anchor on the support plane, a material; unknown keys are errors;
- a data set's render description (the shared ``ar/virtual_scene.json``, recognised by its
  top-level ``world_from_cam0``): names, meshes, ``albedo_rgb`` and poses are read, its
  descriptive keys (mesh_facts, placement, ...) ignored.

Every error is a `SceneError` naming the file and the object and saying what to do.
"""

from __future__ import annotations

import json
import struct
import sys
import urllib.parse
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
import open3d as o3d

from arlight.pipeline.virtual_scene import (
    MAX_OBJECTS,
    MAX_TRIANGLES,
    PRIMITIVES,
    Anchor,
    Material,
    SceneError,
    VirtualObject,
    VirtualScene,
    object_from_open3d,
)

FRAMES = ("world", "cam0")  # --scene-frame: which pose key of the file is the run's world
MESH_SUFFIXES = (".ply", ".obj", ".glb", ".gltf")  # what open3d.io reads (tested)
SCENE_KEYS = ("objects", "description")
OBJECT_KEYS = (
    "name",
    "mesh",
    "primitive",
    "world_from_object",
    "cam0_from_object",
    "anchor",
    "scale",
    "material",
    "albedo_rgb",
)
MATERIAL_KEYS = ("albedo", "roughness", "metalness", "mirror")
ANCHOR_KEYS = ("pixel", "yaw_deg")
PRIMITIVE_KEYS = {
    "sphere": ("radius_m",),
    "box": ("size_m",),
    "torus": ("ring_radius_m", "tube_radius_m"),
}
DATASET_MARK = "world_from_cam0"  # top-level key of a data set's render description


def load_virtual_scene(path: str | Path, frame: str = "world") -> VirtualScene:
    """The virtual scene described by a JSON (or, Python >= 3.11, TOML) file.

    frame: "world" poses objects by `world_from_object` (the sequence's ground-truth world,
    for runs with given poses); "cam0" by `cam0_from_object` (the first camera's OpenCV frame,
    for tracked runs). Mesh paths are relative to the file and stay inside its folder (so do
    the files a mesh names: glTF buffers and images, OBJ materials and textures). Meshes are
    in metres, object frame (origin at the base centre, +y up).
    """
    path = Path(path)
    if frame not in FRAMES:
        raise SceneError(f"--scene-frame must be world or cam0, got {frame!r}")
    doc = _read_document(path)
    if not isinstance(doc, dict):
        raise SceneError(
            f'scene file {path}: expected an object with an "objects" list at '
            "the top level (see docs/scene-files.md)"
        )
    strict = DATASET_MARK not in doc
    if strict:
        _check_keys(doc, SCENE_KEYS, f"scene file {path}")
    entries = doc.get("objects")
    if not isinstance(entries, list) or not entries:
        raise SceneError(
            f'scene file {path}: "objects" must be a non-empty list of objects '
            "(see docs/scene-files.md)"
        )
    if len(entries) > MAX_OBJECTS:
        raise SceneError(
            f"scene file {path}: {len(entries)} objects, at most {MAX_OBJECTS}; remove some"
        )
    objects: list[VirtualObject] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(entries):
        name = entry.get("name") if isinstance(entry, dict) else None
        if not isinstance(name, str) or not name.strip():
            raise SceneError(
                f'scene file {path}, objects[{i}]: needs an object with a non-empty string "name"'
            )
        if name in seen:
            raise SceneError(
                f"scene file {path}, object {name!r}: the name is used by "
                f"objects[{seen[name]}] and objects[{i}]; names must be unique"
            )
        seen[name] = i
        where = f"scene file {path}, object {name!r}"
        budget = MAX_TRIANGLES - sum(len(o.triangles) for o in objects)
        try:
            objects.append(_load_object(entry, path.parent, frame, strict, budget, where))
        except SceneError as exc:
            text = str(exc)
            raise SceneError(
                text if text.startswith("scene file") else f"scene file {path}: {text}"
            ) from None
    return VirtualScene(tuple(objects))


def _read_document(path: Path) -> Any:
    """The parsed JSON or TOML document (dicts, lists, numbers, strings)."""
    suffix = path.suffix.lower()
    if suffix not in (".json", ".toml"):
        raise SceneError(f"scene file {path}: must end in .json or .toml")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SceneError(f"scene file {path} not found; check the path") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"scene file {path} cannot be read ({exc})") from None
    if suffix == ".toml":
        if sys.version_info >= (3, 11):
            import tomllib

            try:
                return tomllib.loads(text)
            except tomllib.TOMLDecodeError as exc:
                raise SceneError(f"scene file {path} is not valid TOML: {exc}") from None
        raise SceneError(
            f"scene file {path}: TOML needs Python >= 3.11 (tomllib); write the scene as JSON"
        )
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise SceneError(
            f"scene file {path} is not valid JSON: {exc.msg} at line "
            f"{exc.lineno}, column {exc.colno}"
        ) from None


def _load_object(
    entry: dict, folder: Path, frame: str, strict: bool, budget: int, where: str
) -> VirtualObject:
    """One object of the file; `where` names it in errors; `budget`: triangles left."""
    if strict:
        _check_keys(entry, OBJECT_KEYS, where)
    if ("mesh" in entry) == ("primitive" in entry):
        raise SceneError(
            f'{where}: give exactly one of "mesh" (a {"/".join(MESH_SUFFIXES)} '
            'file) and "primitive"'
        )
    if "mesh" in entry:
        if not isinstance(entry["mesh"], str):
            raise SceneError(f'{where}: "mesh" must be a file path (relative to the scene file)')
        mesh = _read_mesh(_inside(folder, entry["mesh"], where, "mesh"), budget, where)
    else:
        mesh = _primitive(entry["primitive"], where)
    if len(mesh.triangles) > budget:
        raise _too_many(len(mesh.triangles), budget, where)
    world_from_object, anchor = _pose(entry, frame, where)
    if "scale" in entry:
        scale = _numbers(entry["scale"], (), where, "scale")
        if not scale > 0:
            raise SceneError(f'{where}: "scale" must be > 0, got {float(scale):g}')
        world_from_object = world_from_object @ np.diag([scale, scale, scale, 1.0])
    return object_from_open3d(
        entry["name"], mesh, world_from_object, _material(entry, where), anchor
    )


def _read_mesh(file: Path, budget: int, where: str) -> o3d.geometry.TriangleMesh:
    """A triangle mesh read by Open3D, checked: not empty, not truncated; a PLY whose header
    announces more than `budget` triangles is refused before it is read."""
    if file.suffix.lower() not in MESH_SUFFIXES:
        raise SceneError(f"{where}: mesh {file} must be one of {', '.join(MESH_SUFFIXES)}")
    if not file.is_file():
        raise SceneError(
            f"{where}: mesh file {file} not found (mesh paths are relative to the scene file)"
        )
    _check_references(file, where)
    try:
        counts = _ply_counts(file) if file.suffix.lower() == ".ply" else None
    except OSError as exc:
        raise SceneError(f"{where}: mesh {file} cannot be read ({exc})") from None
    if counts is not None and counts[1] > budget:
        raise _too_many(counts[1], budget, where)
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh = o3d.io.read_triangle_mesh(str(file))
    except RuntimeError as exc:
        raise SceneError(f"{where}: mesh {file} cannot be read ({exc})") from None
    triangles = len(mesh.triangles)
    if triangles == 0:
        raise SceneError(
            f"{where}: mesh {file} holds no triangles (broken, or not a triangle "
            "mesh); re-export it as a triangle mesh (PLY, OBJ, glTF)"
        )
    if counts is not None and (len(mesh.vertices) != counts[0] or triangles < counts[1]):
        raise SceneError(
            f"{where}: mesh {file} is truncated or broken: its header lists "
            f"{counts[0]} vertices and {counts[1]} faces, {len(mesh.vertices)} and "
            f"{triangles} could be read; re-export it"
        )
    return mesh


def _inside(folder: Path, name: str, where: str, what: str) -> Path:
    """`folder / name`, refused (SceneError) unless it stays inside `folder` once links are
    followed: a scene file, or a mesh it names, may read no file outside the scene file's
    folder (an absolute path, ``..``, or a link out of it would send that file's bytes to the
    server as vertex data)."""
    relative = PurePosixPath(name.replace("\\", "/"))
    if not name or relative.is_absolute() or PureWindowsPath(name).drive or ".." in relative.parts:
        raise SceneError(
            f"{where}: {what} {name[:200]!r} must be a relative path inside the scene "
            f"file's folder ({folder}), without '..'; copy the file there"
        )
    file = folder / relative
    try:
        inside = file.resolve().is_relative_to(folder.resolve())
    except (OSError, RuntimeError):  # a link loop
        inside = False
    if not inside:
        raise SceneError(
            f"{where}: {what} {name[:200]!r} leads outside the scene file's folder "
            f"({folder}) through a link; copy the file there"
        )
    return file


def _check_references(file: Path, where: str) -> None:
    """The files a mesh names in turn (a glTF's buffer and image ``uri``s, an OBJ's
    ``mtllib`` and a material's texture maps) must stay inside the mesh's folder too
    (`_inside`); embedded ``data:`` URIs are fine."""
    suffix = file.suffix.lower()
    try:
        if suffix in (".gltf", ".glb"):
            for uri in _gltf_uris(file):
                if not uri.startswith("data:"):
                    _inside(file.parent, urllib.parse.unquote(uri), where, f"{file.name} uri")
        elif suffix == ".obj":
            for library in _obj_names(file, ("mtllib",)):
                mtl = _inside(file.parent, library, where, f"{file.name} mtllib")
                if mtl.is_file():
                    for texture in _obj_names(mtl, MTL_MAPS):
                        _inside(file.parent, texture, where, f"{mtl.name} texture")
    except OSError as exc:
        raise SceneError(f"{where}: mesh {file} cannot be read ({exc})") from None


MTL_MAPS: tuple[str, ...] = (  # the MTL keywords that name a texture file
    *("map_Ka", "map_Kd", "map_Ks", "map_Ns", "map_d", "map_bump", "bump", "disp", "norm"),
    *("map_Pr", "map_Pm", "map_Ps", "map_Ke", "refl", "decal"),
)


def _gltf_uris(file: Path) -> list[str]:
    """Every ``uri`` of a glTF's buffers and images (the JSON chunk of a .glb); [] when the
    file is not readable as one (Open3D then refuses it)."""
    data = file.read_bytes()
    if file.suffix.lower() == ".glb":
        if len(data) < 20 or data[:4] != b"glTF":
            return []
        (length,) = struct.unpack_from("<I", data, 12)
        data = data[20 : 20 + length]
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError):
        return []
    uris = []
    for key in ("buffers", "images"):
        items = doc.get(key) if isinstance(doc, dict) else None
        for item in items if isinstance(items, list) else ():
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str):
                uris.append(uri)
            elif uri is not None:
                uris.append(repr(uri))  # not a string: refused as a path
    return uris


def _obj_names(file: Path, keywords: tuple[str, ...]) -> list[str]:
    """The file names after `keywords` in an OBJ or MTL file (the last word of the line:
    texture options come before the name)."""
    names = []
    with open(file, encoding="utf-8", errors="replace") as f:
        for line in f:
            words = line.split()
            if len(words) >= 2 and words[0] in keywords:
                names.append(words[-1] if words[0] != "mtllib" else " ".join(words[1:]))
    return names


def _ply_counts(file: Path) -> tuple[int, int] | None:
    """(vertices, faces) from a PLY header; None when there is no readable header."""
    with open(file, "rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None
    counts = {}
    for line in head[:end].decode("ascii", "replace").splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[2].isdigit():
            counts[parts[1]] = int(parts[2])
    return counts.get("vertex", 0), counts.get("face", 0)


def _too_many(triangles: int, budget: int, where: str) -> SceneError:
    return SceneError(
        f"{where}: {triangles} triangles, but the scene may hold {MAX_TRIANGLES} "
        f"in all ({max(budget, 0)} left for this object); simplify the mesh "
        "(e.g. Open3D simplify_quadric_decimation)"
    )


def _primitive(spec: Any, where: str) -> o3d.geometry.TriangleMesh:
    """A built-in primitive from {"shape": ..., its sizes in metres}."""
    shape = spec.get("shape") if isinstance(spec, dict) else None
    if shape not in PRIMITIVES:
        raise SceneError(
            f'{where}: "primitive" must be an object with "shape" one of '
            f"{', '.join(PRIMITIVES)}, got {spec!r}"
        )
    _check_keys(spec, ("shape", *PRIMITIVE_KEYS[shape]), f"{where}, {shape}")
    sizes = {}
    for key in PRIMITIVE_KEYS[shape]:
        if key in spec:
            value = _numbers(spec[key], (3,) if key == "size_m" else (), where, key)
            if not np.all(value > 0):
                raise SceneError(f"{where}: {key} must be > 0 metres, got {spec[key]}")
            sizes[key] = tuple(value) if value.ndim else float(value)
    return PRIMITIVES[shape](**sizes)


def _pose(entry: dict, frame: str, where: str) -> tuple[np.ndarray, Anchor | None]:
    """(world_from_object, anchor): the pose key that `frame` picks, or an anchor."""
    key, other = f"{frame}_from_object", f"{FRAMES[1 - FRAMES.index(frame)]}_from_object"
    spec = entry.get("anchor")
    if spec is not None:
        if key in entry or other in entry:
            raise SceneError(f'{where}: give a pose ({key}) or an "anchor", not both')
        if not isinstance(spec, dict):
            raise SceneError(
                f'{where}: "anchor" must be an object {{"pixel": [u, v] or null, "yaw_deg": 0}}'
            )
        _check_keys(spec, ANCHOR_KEYS, f"{where}, anchor")
        pixel = spec.get("pixel")
        if pixel is not None:
            pixel = tuple(float(x) for x in _numbers(pixel, (2,), where, "anchor pixel"))
        yaw_deg = float(_numbers(spec.get("yaw_deg", 0.0), (), where, "anchor yaw_deg"))
        return np.eye(4), Anchor(pixel, yaw_deg)
    if key in entry:
        return _numbers(entry[key], (4, 4), where, key), None
    if other in entry:
        raise SceneError(
            f"{where}: has {other} but no {key}; run with --scene-frame "
            f"{other.split('_')[0]} or add {key}"
        )
    raise SceneError(
        f'{where}: needs a pose ("{key}": 4x4 row-major) or an "anchor" '
        '({"pixel": [u, v] or null, "yaw_deg": 0})'
    )


def _material(entry: dict, where: str) -> Material:
    """The object's Material from "material" and/or a top-level "albedo_rgb"."""
    spec = entry.get("material", {})
    if not isinstance(spec, dict):
        raise SceneError(
            f'{where}: "material" must be an object with keys {", ".join(MATERIAL_KEYS)}'
        )
    _check_keys(spec, MATERIAL_KEYS, f"{where}, material")
    if "albedo" in spec and "albedo_rgb" in entry:
        raise SceneError(f"{where}: give the albedo once (material.albedo or albedo_rgb)")
    kwargs: dict[str, Any] = {}
    albedo = spec.get("albedo", entry.get("albedo_rgb"))
    if albedo is not None:
        kwargs["albedo"] = tuple(float(x) for x in _numbers(albedo, (3,), where, "albedo"))
    for key in ("roughness", "metalness"):
        if key in spec:
            value = float(_numbers(spec[key], (), where, key))
            if not 0.0 <= value <= 1.0:
                raise SceneError(f"{where}: {key} must be in [0, 1], got {value:g}")
            kwargs[key] = value
    if "mirror" in spec:
        if not isinstance(spec["mirror"], bool):
            raise SceneError(f"{where}: mirror must be true or false, got {spec['mirror']!r}")
        kwargs["mirror"] = spec["mirror"]
    return Material(**kwargs)


def _numbers(value: Any, shape: tuple[int, ...], where: str, field: str) -> np.ndarray:
    """`value` (nested lists of JSON numbers) as a finite float64 array of `shape`."""
    expected = "a number" if shape == () else "numbers of shape " + "x".join(map(str, shape))
    try:
        a = np.array(value, dtype=object)
    except ValueError:
        a = np.array(None)
    if a.shape != shape or not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in a.flat
    ):
        raise SceneError(f"{where}: {field} must be {expected}, got {value!r}")
    try:
        out = a.astype(np.float64)
    except OverflowError:
        out = np.array([np.inf])
    if not np.all(np.isfinite(out)):
        raise SceneError(f"{where}: {field} must be finite (NaN or inf found)")
    return out


def _check_keys(spec: dict, valid: tuple[str, ...], where: str) -> None:
    unknown = sorted(set(spec) - set(valid))
    if unknown:
        raise SceneError(
            f"{where}: unknown key(s) {', '.join(unknown)}; valid keys: {', '.join(valid)}"
        )
