#!/usr/bin/python3
"""Writes the crafted inputs of this folder (see README.md): each one crashed, hung or misbehaved
in an earlier backlight and must now give a one-line error with exit status 2. Deterministic;
run it from anywhere to regenerate the files."""
import base64
import json
import os
import struct
import zlib

HERE = os.path.dirname(os.path.abspath(__file__))


def write(name, data):
    with open(os.path.join(HERE, name), "wb" if isinstance(data, bytes) else "w") as f:
        f.write(data)


def gltf(accessors, buffer_bytes, nodes=None, extra=None, cameras=None):
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(buffer_bytes),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(buffer_bytes).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(buffer_bytes)}],
        "accessors": accessors,
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": nodes or [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    if cameras:
        doc["cameras"] = cameras
    if extra:
        doc.update(extra)
    return json.dumps(doc)


triangle = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
pos = {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}

# 1. Size arithmetic that wrapped around: counts near 2^62 and 2^64, an offset near 2^64.
write("gltf_count_2p62.gltf", gltf([dict(pos, count=2**62)], triangle))
write("gltf_count_2p64.gltf", gltf([dict(pos, count=2**64 - 1)], triangle))
write("gltf_offset_2p64.gltf", gltf([dict(pos, byteOffset=2**64 - 8)], triangle))
# 2. Unbounded recursion: 48 000-deep `extras` (tinygltf 2.7.0's parser overflows the stack from
# about 20 000 levels), a deep scene and config. 48 000 keeps each file under 100 KB.
DEEP = 48000
write("gltf_deep_extras.gltf", gltf([pos], triangle, extra={"extras": "@"}).replace('"@"', "[" * DEEP + "]" * DEEP))
write("scene_deep.json", '{"cameras": ' + "[" * DEEP + "]" * DEEP + "}")
# 3. A node graph that is a DAG, not a tree: node k lists node k+1 twice (2^40 paths).
dag = [{"children": [k + 1, k + 1]} for k in range(40)] + [{"mesh": 0}]
write("gltf_dag.gltf", gltf([pos], triangle, nodes=dag))
# 4. Non-finite cameras: coordinates near 3e38, a default camera fitted to overflowing bounds.
huge = struct.pack("<9f", -3e38, -3e38, 0, 3e38, -3e38, 0, 0, 3e38, 0)
write("gltf_huge_bounds.gltf", gltf([pos], huge))
write("scene_camera_3e38.json", json.dumps({
    "cameras": [{"origin": [3e38, 3e38, 3e38], "target": [-3e38, -3e38, -3e38], "fov": 40}],
    "materials": {"m": {"type": "diffuse", "albedo": 0.5}},
    "shapes": [{"name": "r", "type": "rectangle", "material": "m"}]}))
# 5. Sizes before allocation: a glTF camera whose aspect ratio asks for a 512 x 51 200 000 film.
write("gltf_aspect_1e-5.gltf", gltf([pos], triangle, nodes=[{"mesh": 0, "children": [1]}, {"camera": 0}],
                                    cameras=[{"type": "perspective",
                                              "perspective": {"yfov": 0.8, "aspectRatio": 1e-5, "znear": 0.01}}]))


def png_chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xffffffff)


# A 69-byte PNG whose header says 100000 x 100000 RGB pixels (120 GB as floats).
png = b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", struct.pack(">IIBBBBB", 100000, 100000, 8, 2, 0, 0, 0)) + \
    png_chunk(b"IDAT", zlib.compress(b"\0")) + png_chunk(b"IEND", b"")
write("image_png_100000x100000.png", png)


# An OpenEXR header whose string attribute claims 1.7 GB (OpenEXR allocates it before noticing).
def exr_attr(name, kind, value):
    return name + b"\0" + kind + b"\0" + struct.pack("<i", len(value)) + value


exr = struct.pack("<I", 20000630) + struct.pack("<I", 2) + \
    exr_attr(b"channels", b"chlist", b"R\0" + struct.pack("<iBBBBii", 2, 0, 0, 0, 0, 1, 1) + b"\0") + \
    b"comment\0string\0" + struct.pack("<i", 1700000000) + b"x" * 64 + b"\0"
write("image_exr_attribute_1p7GB.exr", exr)

# Optimizer configs (scene path relative to this folder; "output" must never be created).
config = {"scene": "../../../scenes/cornell/scene.json", "output": "out-must-not-exist",
          "parameters": {"wall.albedo": {"lr": 0.01}},
          "views": {"cameras": [0], "reference": {"set": {"wall.albedo": 0.5}, "spp": 1}}, "iterations": 1}
deep = dict(config)
write("config_deep_init.json", json.dumps(deep).replace('{"lr": 0.01}', '{"lr": 0.01, "init": ' + "[" * DEEP +
                                                        "]" * DEEP + "}"))
write("config_resolution_huge.json", json.dumps(dict(config, resolution=[2000000000, 2000000000])))
schedule = json.loads(json.dumps(config))
schedule["parameters"]["wall.albedo"]["schedule"] = [{"until": 1, "resolution": [100000, 100000]}]
write("config_schedule_huge.json", json.dumps(schedule))
write("config_camera_index_2p40.json", json.dumps(dict(config, views={"cameras": [2**40], "reference": {"set": {"wall.albedo": 0.5}, "spp": 1}})))
write("config_spp_2p31.json", json.dumps(dict(config, spp=2**31 - 1)))


# The same deep JSON inside a binary glTF's JSON chunk.
def glb(json_text):
    body = json_text.encode()
    body += b" " * (-len(body) % 4)
    chunk = struct.pack("<I4s", len(body), b"JSON") + body
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunk)) + chunk


write("gltf_deep_extras.glb", glb(gltf([pos], triangle, extra={"extras": "@"}).replace('"@"', "[" * DEEP + "]" * DEEP)))


# 6. Amplification: a small file whose parts are counted many times. One 2000-vertex accessor in
# 500 primitives of a mesh instanced by 3000 nodes (3 * 10^9 vertices from 94 KB); one 2048^2
# texture (a 12 KB PNG of zeros) as base colour of 400 materials (each gets its own 50 MB copy).
n = 2000
verts = b"".join(struct.pack("<3f", i % 7, (i * 3) % 5, (i * 5) % 11) for i in range(n))
many = {"asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(verts),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(verts).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(verts)}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": n - n % 3, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}] * 500}],
        "nodes": [{"children": list(range(1, 3001))}] + [{"mesh": 0}] * 3000, "scenes": [{"nodes": [0]}], "scene": 0}
write("gltf_instances_3e9_vertices.gltf", json.dumps(many, separators=(",", ":")))
side = 2048
z = zlib.compressobj(9)
idat = b"".join(z.compress(b"\0" * (1 + side * 3)) for _ in range(side)) + z.flush()
texture = b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)) + \
    png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")
uv_tri = triangle + struct.pack("<6f", 0, 0, 1, 0, 0, 1)
materials = 400
shared = {"asset": {"version": "2.0"},
          "buffers": [{"byteLength": len(uv_tri),
                       "uri": "data:application/octet-stream;base64," + base64.b64encode(uv_tri).decode()}],
          "bufferViews": [{"buffer": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 24}],
          "accessors": [pos, {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"}],
          "images": [{"uri": "data:image/png;base64," + base64.b64encode(texture).decode()}],
          "textures": [{"source": 0}],
          "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}] * materials,
          "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "material": m}
                                     for m in range(materials)]}],
          "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0}
write("gltf_texture_in_400_materials.gltf", json.dumps(shared, separators=(",", ":")))

# Mitsuba XML: 20 000 nested elements (the XML walk recurses; the limit is 64), and the "billion
# laughs" entity expansion (pugixml does not expand DTD entities: the value stays '&lol9;').
write("scene_xml_deep.xml", '<scene version="3.0.0">' + '<shape type="obj">' * 20000 + "</shape>" * 20000 +
      "</scene>\n")
laughs = '<?xml version="1.0"?>\n<!DOCTYPE scene [\n<!ENTITY lol "lol">\n'
for i in range(1, 10):
    laughs += f'<!ENTITY lol{i} "' + ("&lol;" if i == 1 else f"&lol{i - 1};") * 10 + '">\n'
laughs += (']>\n<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="&lol9;"/></sensor>'
           '<shape type="rectangle"/></scene>\n')
write("scene_xml_billion_laughs.xml", laughs)
