"""A scene file may read no local file outside its own folder (issue 39, item 7): a mesh path
that is absolute, climbs with `..` or leaves through a link, and a glTF buffer or image `uri`
(or an OBJ material or texture) that does, is refused with a SceneError naming the object,
which `arlight stream --scene` reports as bad input (exit 2, naming --scene). Before, a
`.gltf` buffer uri of ../../secret/credentials.txt was read and its bytes went to the server
as vertex data."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from arlight.pipeline.virtual_scene import SceneError
from arlight.sources.virtual_scene_file import load_virtual_scene


def _scene(folder: Path, mesh: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scene.json"
    entry = {"name": "thing", "mesh": mesh, "world_from_object": np.eye(4).tolist()}
    path.write_text(json.dumps({"objects": [entry]}))
    return path


def _gltf_with_buffer_file(folder: Path, uri: str, buffer_file: Path) -> None:
    """A box as folder/box.gltf whose one buffer is the file `buffer_file`, named by `uri`."""
    folder.mkdir(parents=True, exist_ok=True)
    o3d.io.write_triangle_mesh(str(folder / "box.gltf"), o3d.geometry.TriangleMesh.create_box())
    doc = json.loads((folder / "box.gltf").read_text())
    embedded = doc["buffers"][0]["uri"]
    buffer_file.parent.mkdir(parents=True, exist_ok=True)
    buffer_file.write_bytes(base64.b64decode(embedded.split(",", 1)[1]))
    doc["buffers"][0]["uri"] = uri
    (folder / "box.gltf").write_text(json.dumps(doc))


def test_gltf_buffer_in_the_scene_folder_loads(tmp_path: Path):
    scene = tmp_path / "scene"
    _gltf_with_buffer_file(scene, "box.bin", scene / "box.bin")
    loaded = load_virtual_scene(_scene(scene, "box.gltf"))
    assert len(loaded.objects[0].triangles) == 12


def test_gltf_buffer_outside_the_scene_folder_is_refused(tmp_path: Path):
    scene = tmp_path / "a" / "b"
    secret = tmp_path / "secret" / "credentials.txt"
    _gltf_with_buffer_file(scene, "../../secret/credentials.txt", secret)
    with pytest.raises(SceneError, match=r"object 'thing'.*\.\./\.\./secret/credentials\.txt"):
        load_virtual_scene(_scene(scene, "box.gltf"))
    # percent-encoded and absolute uris too
    for uri in ("%2E%2E/%2E%2E/secret/credentials.txt", secret.as_uri(), str(secret)):
        _gltf_with_buffer_file(scene, uri, secret)
        with pytest.raises(SceneError, match="object 'thing'"):
            load_virtual_scene(_scene(scene, "box.gltf"))


def test_gltf_image_uri_outside_is_refused(tmp_path: Path):
    scene = tmp_path / "scene"
    _gltf_with_buffer_file(scene, "box.bin", scene / "box.bin")
    doc = json.loads((scene / "box.gltf").read_text())
    doc["images"] = [{"uri": "../../../../etc/passwd"}]
    (scene / "box.gltf").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="etc/passwd"):
        load_virtual_scene(_scene(scene, "box.gltf"))


@pytest.mark.parametrize("where", ["parent", "absolute", "link"])
def test_mesh_path_outside_the_scene_folder_is_refused(tmp_path: Path, where: str):
    outside = tmp_path / "private" / "box.ply"
    outside.parent.mkdir()
    o3d.io.write_triangle_mesh(str(outside), o3d.geometry.TriangleMesh.create_box())
    scene = tmp_path / "scene"
    scene.mkdir()
    name = {"parent": "../private/box.ply", "absolute": str(outside), "link": "box.ply"}[where]
    if where == "link":
        (scene / "box.ply").symlink_to(outside)
    with pytest.raises(SceneError, match="scene file's folder"):
        load_virtual_scene(_scene(scene, name))


def test_obj_material_and_texture_outside_are_refused(tmp_path: Path):
    scene = tmp_path / "scene"
    scene.mkdir()
    o3d.io.write_triangle_mesh(str(scene / "box.obj"), o3d.geometry.TriangleMesh.create_box())
    body = (scene / "box.obj").read_text()
    (scene / "box.obj").write_text("mtllib ../../outside.mtl\n" + body)
    with pytest.raises(SceneError, match="outside.mtl"):
        load_virtual_scene(_scene(scene, "box.obj"))
    (scene / "box.mtl").write_text("newmtl m\nmap_Kd -s 1 1 1 /etc/hostname\n")
    (scene / "box.obj").write_text("mtllib box.mtl\n" + body)
    with pytest.raises(SceneError, match="/etc/hostname"):
        load_virtual_scene(_scene(scene, "box.obj"))


def test_stream_names_the_flag_and_exits_2(tmp_path: Path, capsys):
    from conftest import run_cli

    scene = tmp_path / "a" / "b"
    _gltf_with_buffer_file(scene, "../../secret/credentials.txt", tmp_path / "secret" / "c.txt")
    code, err = run_cli(
        [
            "stream",
            "--server",
            "tcp://127.0.0.1:1",
            "--scene",
            str(_scene(scene, "box.gltf")),
            "synthetic",
        ],
        capsys,
    )
    assert code == 2, err
    assert "--scene" in err and "secret" in err and "Traceback" not in err
