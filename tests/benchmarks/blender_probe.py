"""Run inside Blender (headless) by interop_check.py: import a GLB, check it, evaluate it, render it.

    blender -b --factory-startup --python blender_probe.py -- AVATAR.glb OUT_STEM 0,3,6 render|norender

Writes OUT_STEM.json (armature, skin, texture, animation facts, bone heights), OUT_STEM.frame<k>.f64
(the evaluated skinned mesh's vertex coordinates at the k-th requested animation key, float64
(V, 3) in the mesh object's space; its matrix_world is in the JSON) and, with `render`,
OUT_STEM.png (Cycles, front view, 16 samples). Uses only bpy and the standard library (Debian's
Blender runs on the system Python, which need not have numpy).
"""

import json
import math
import struct
import sys
from array import array
from pathlib import Path

import bpy
from mathutils import Vector

argv = sys.argv[sys.argv.index("--") + 1:]
glb_path, out_stem, frames_arg, render_arg = argv[0], Path(argv[1]), argv[2], argv[3]
keys = [int(k) for k in frames_arg.split(",") if k]


def glb_json(path):
    """The GLB's JSON chunk (to read the clip's fps before importing)."""
    data = Path(path).read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


doc = glb_json(glb_path)
animations = doc.get("animations", [])
fps = float(animations[0].get("extras", {}).get("fps", 30.0)) if animations else 30.0

# Debian 12 pairs Blender 3.4 with numpy 1.24, which removed the `np.bool` alias that Blender's
# glTF importer still uses (skinning import); restore the alias for the importer only.
try:
    import numpy

    if "bool" not in numpy.__dict__:
        numpy.bool = bool
except ImportError:  # the importer itself needs numpy: apt-get install python3-numpy
    pass

bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
# Keys land on whole frames when the scene plays at the clip's rate.
scene.render.fps = int(round(fps))
scene.render.fps_base = scene.render.fps / fps
bpy.ops.import_scene.gltf(filepath=glb_path)

armatures = [o for o in scene.objects if o.type == "ARMATURE"]
meshes = [o for o in scene.objects if o.type == "MESH"]
report = {"file": glb_path, "objects": len(scene.objects), "armatures": len(armatures), "meshes": len(meshes),
          "blender": bpy.app.version_string}
mesh = meshes[0]
armature = armatures[0] if armatures else None
if armature is not None:
    bones = armature.data.bones
    report["bones"] = len(bones)
    world = {b.name: list(armature.matrix_world @ b.head_local) for b in bones}
    heads = [n for n in world if n.lower() == "head"]
    feet = [n for n in world if n.lower().startswith("foot")]
    if heads and feet:
        report["head_z"] = world[heads[0]][2]
        report["feet_z"] = max(world[f][2] for f in feet)
        report["head_above_feet_m"] = report["head_z"] - report["feet_z"]
report["vertices"] = len(mesh.data.vertices)
report["faces"] = len(mesh.data.polygons)
report["vertex_groups"] = len(mesh.vertex_groups)
report["armature_modifier"] = any(m.type == "ARMATURE" and m.object is armature for m in mesh.modifiers)
influences = [sum(1 for g in v.groups if g.weight > 0) for v in mesh.data.vertices]
report["max_influences"] = max(influences) if influences else 0
dims = mesh.dimensions
report["dimensions_xyz_m"] = [dims.x, dims.y, dims.z]
# Where the avatar stands in the rest pose: the lowest vertex (the floor is Z = 0 in Blender) and the
# horizontal centre of its feet.
rest_world = [mesh.matrix_world @ v.co for v in mesh.data.vertices]
report["rest_min_z_m"] = min(c.z for c in rest_world)
report["rest_max_z_m"] = max(c.z for c in rest_world)
low = [c for c in rest_world if c.z < report["rest_min_z_m"] + 0.05]
report["feet_center_xy_m"] = [sum(c.x for c in low) / len(low), sum(c.y for c in low) / len(low)]

textures = []
for slot in mesh.material_slots:
    material = slot.material
    if material is None or not material.use_nodes:
        continue
    for node in material.node_tree.nodes:
        if node.type == "TEX_IMAGE" and node.image is not None:
            linked = any(link.to_socket.name == "Base Color" for link in node.outputs["Color"].links)
            textures.append({"image": node.image.name, "size": list(node.image.size), "to_base_color": linked})
report["textures"] = textures
report["vertex_colors"] = len(getattr(mesh.data, "color_attributes", []))

action = armature.animation_data.action if armature is not None and armature.animation_data else None
report["action"] = None if action is None else {
    "name": action.name, "frame_range": list(action.frame_range), "fcurves": len(action.fcurves),
    "actions_total": len(bpy.data.actions),
}
report["fps"] = fps

if action is not None:
    start = action.frame_range[0]
    files, matrices, first, moved = [], [], None, 0.0
    for k, key in enumerate(keys):
        scene.frame_set(int(round(start + key)))
        depsgraph = bpy.context.evaluated_depsgraph_get()
        evaluated = mesh.evaluated_get(depsgraph)
        data = evaluated.to_mesh()
        co = array("d", bytes(8 * 3 * len(data.vertices)))
        data.vertices.foreach_get("co", co)
        evaluated.to_mesh_clear()
        path = f"{out_stem}.frame{k}.f64"
        Path(path).write_bytes(co.tobytes())
        files.append(path)
        matrices.append([list(row) for row in evaluated.matrix_world])
        if first is None:
            first = co
        else:  # the clip plays: the mesh moves between the evaluated keys
            moved = max(moved, max(math.dist(first[i:i + 3], co[i:i + 3]) for i in range(0, len(co), 3)))
    report["evaluated_frames"] = [start + key for key in keys]
    report["vertex_files"] = files
    report["matrix_world"] = matrices
    report["motion_between_keys_mm"] = moved * 1e3

if render_arg == "render":
    scene.frame_set(int(action.frame_range[0]) if action is not None else 0)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    corners = [mesh.evaluated_get(depsgraph).matrix_world @ Vector(c) for c in mesh.evaluated_get(depsgraph).bound_box]
    low = Vector([min(c[i] for c in corners) for i in range(3)])
    high = Vector([max(c[i] for c in corners) for i in range(3)])
    center = (low + high) / 2
    height = high.z - low.z
    camera_data = bpy.data.cameras.new("camera")
    camera_data.lens = 50
    camera = bpy.data.objects.new("camera", camera_data)
    scene.collection.objects.link(camera)
    # The subject faces -Y in Blender (glTF +Z forward); the camera looks along +Y at it.
    camera.location = (center.x, center.y - 2.2 * height, center.z)
    camera.rotation_euler = (math.pi / 2, 0.0, 0.0)
    scene.camera = camera
    sun_data = bpy.data.lights.new("sun", type="SUN")
    sun_data.energy = 3.0
    sun = bpy.data.objects.new("sun", sun_data)
    sun.rotation_euler = (math.radians(50), 0.0, math.radians(-20))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs[0].default_value = (1.0, 1.0, 1.0, 1.0)
    world.node_tree.nodes["Background"].inputs[1].default_value = 0.8
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False  # Debian's build has no OpenImageDenoise
    scene.render.resolution_x, scene.render.resolution_y = 400, 600
    scene.render.filepath = str(out_stem) + ".png"
    bpy.ops.render.render(write_still=True)
    report["render"] = str(out_stem) + ".png"

Path(str(out_stem) + ".json").write_text(json.dumps(report, indent=1))
