#!/usr/bin/python3
"""Generates the binary assets of the example scenes.

    scenes/cornell/wall.png      1024x1024 RGB albedo texture of the Cornell box's back wall
    scenes/gltf/checker.png      256x256 RGB base-colour texture of the glTF ground plane
    scenes/gltf/scene.gltf/.bin  a small glTF 2.0 scene (ground, two cubes, emissive quad, camera)
    scenes/smoke/density.vdb     128³ procedural smoke density (OpenVDB, float grid "density", the
                                 scene's; not committed)
    scenes/smoke/density.vol     the same grid as a Mitsuba .vol (for Mitsuba and the benchmarks)
    scenes/smoke/sky.pfm         64x32 sky environment map (latitude-longitude, linear RGB)
    scenes/deform/sphere.ply     unit icosphere (4 subdivisions: 2562 vertices, 5120 triangles)
    scenes/deform/target.ply     the same vertices moved onto a smooth non-spherical blob

`--smoke` makes only the smoke assets (what `tools/quickstart volume` needs).

Deterministic and idempotent: runs from any working directory, writes a file only when its bytes
change, and reads every output back to check it. Needs Debian's python3 with numpy and matplotlib
(Pillow, a matplotlib dependency, writes the RGB PNGs); the smoke's .vdb needs python3-openvdb.
"""

import io
import json
import math
import struct
import sys
from pathlib import Path

import numpy as np
import matplotlib

matplotlib.use("Agg")
matplotlib.rcdefaults()  # ignore any user matplotlibrc: the output must not depend on it
import matplotlib.image as mpimg  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Circle, Polygon, Rectangle, Wedge  # noqa: E402
from PIL import Image  # noqa: E402

SCENES = Path(__file__).resolve().parent
CORNELL = SCENES / "cornell"
GLTF = SCENES / "gltf"

# Albedo range: every 8-bit sRGB value stays in [LO, HI], i.e. about 0.05 .. 0.84 linear.
LO, HI = 64, 235


def srgb_to_linear(c):
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def write_if_changed(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists() and path.read_bytes() == data:
        print(f"unchanged {path.relative_to(SCENES.parent)} ({len(data)} bytes)")
        return
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    print(f"wrote     {path.relative_to(SCENES.parent)} ({len(data)} bytes)")


def png_bytes(rgb):
    """RGB uint8 array (row 0 = top) -> PNG file bytes, without timestamps or other metadata."""
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    buf = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def render_figure(size, draw):
    """Draws with matplotlib (Agg) on a size x size pixel canvas whose data coordinates are pixel
    coordinates, x right and y down (row 0 = top), and returns the clamped RGB uint8 image."""
    dpi = 128
    fig = Figure(figsize=(size / dpi, size / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    ax.set_xlim(0, size)
    ax.set_ylim(size, 0)
    ax.set_autoscale_on(False)
    draw(ax)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    assert rgba.shape == (size, size, 4), rgba.shape
    return np.clip(rgba[:, :, :3], LO, HI).astype(np.uint8)


def c8(hexstr):
    """'#rrggbb' -> matplotlib colour, checked to lie in the albedo range."""
    v = [int(hexstr[i:i + 2], 16) for i in (1, 3, 5)]
    assert all(LO <= x <= HI for x in v), hexstr
    return tuple(x / 255 for x in v)


# ----------------------------------------------------------------------------------------------
# Cornell box back wall
# ----------------------------------------------------------------------------------------------

BG = c8("#e6dcc8")      # warm paper
INK = c8("#404a7a")     # dark navy text
INK2 = c8("#7a4a40")    # dark brown text
PALETTE = [c8(h) for h in ("#c84646", "#e09a40", "#dcc850", "#5aa050", "#4088c0", "#7a5ab4", "#c860a0")]


def draw_wall(ax):
    W = 1024
    text = dict(family="DejaVu Sans", ha="center", va="center")
    ax.add_patch(Rectangle((0, 0), W, W, color=BG, lw=0))

    # Top: hue gradient band (a smooth ramp through the palette), then a grey ramp below it.
    ramp = np.linspace(0, len(PALETTE) - 1, W)
    cols = np.array(PALETTE)
    lo = np.floor(ramp).astype(int).clip(0, len(PALETTE) - 2)
    t = (ramp - lo)[:, None]
    band = (1 - t) * cols[lo] + t * cols[lo + 1]
    ax.imshow(band[None, :, :], extent=(0, W, 64, 0), interpolation="bilinear", aspect="auto", zorder=2)
    grey = np.linspace(LO / 255, HI / 255, W)
    ax.imshow(np.repeat(grey[None, :, None], 3, axis=2), extent=(0, W, 88, 64), interpolation="bilinear",
              aspect="auto", zorder=2)

    # Title and text lines (the upper half stays visible behind the objects in the box).
    ax.text(W / 2, 205, "backlight", fontsize=100, weight="bold", color=INK, **text)
    ax.text(W / 2, 322, "differentiable path tracing", fontsize=34, color=INK2, **text)
    ax.text(W / 2, 380, "wall.albedo  \u00b7  1024 \u00d7 1024  \u00b7  row 0 at the top", fontsize=22,
            color=INK, **text)
    ax.text(W / 2, 420, "ABCDEFGHIJKLMNOPQRSTUVWXYZ  0123456789", fontsize=20, family="DejaVu Sans Mono",
            color=INK2, ha="center", va="center")
    ax.add_patch(Rectangle((112, 446), W - 224, 6, color=INK, lw=0))

    # Middle: resolution bars (vertical, then horizontal) of 32, 16, 8, 4 and 2 pixel periods.
    x0, y0, h = 64, 476, 150
    for period in (32, 16, 8, 4, 2):
        for k in range(0, 64, period):
            ax.add_patch(Rectangle((x0 + k, y0), period / 2, h, color=INK, lw=0))
        x0 += 64 + 12
    y = y0
    for period in (16, 8, 4):
        for k in range(0, 48, period):
            ax.add_patch(Rectangle((x0, y + k), 64, period / 2, color=INK2, lw=0))
        y += 48 + 3

    # Middle right: coloured shapes.
    ax.add_patch(Circle((610, 551), 64, color=PALETTE[0], lw=0))
    ax.add_patch(Polygon([(700, 616), (770, 486), (840, 616)], closed=True, color=PALETTE[3], lw=0))
    ax.add_patch(Rectangle((866, 486), 130, 130, color=PALETTE[4], lw=0))
    ax.add_patch(Circle((931, 551), 38, color=PALETTE[2], lw=0))
    ax.add_patch(Wedge((610, 551), 40, 20, 160, color=PALETTE[2], lw=0))

    # Bottom centre: an 11x11 checker with a marked corner; bottom sides: stripes and colour patches.
    cx, cy, n, s = 336, 656, 11, 32
    for i in range(n):
        for j in range(n):
            ax.add_patch(Rectangle((cx + j * s, cy + i * s), s, s, lw=0,
                                   color=INK if (i + j) % 2 == 0 else c8("#d2c8b4")))
    ax.add_patch(Rectangle((cx, cy), 2 * s, 2 * s, color=PALETTE[0], lw=0))
    ax.add_patch(Rectangle((cx + (n - 2) * s, cy + (n - 2) * s), 2 * s, 2 * s, color=PALETTE[4], lw=0))
    for k, col in enumerate(PALETTE):  # diagonal stripes on the left
        ax.add_patch(Polygon([(0, 680 + 52 * k), (280, 630 + 52 * k), (280, 656 + 52 * k), (0, 706 + 52 * k)],
                             closed=True, color=col, lw=0))
    for k, col in enumerate(PALETTE[::-1]):  # colour patches with labels on the right
        yk = 656 + 52 * k
        ax.add_patch(Rectangle((744, yk), 216, 44, color=col, lw=0))
        ax.text(852, yk + 22, f"albedo {k + 1}", fontsize=15, color=c8("#ebe6dc") if k % 2 else INK, **text)


def make_wall():
    img = render_figure(1024, draw_wall)
    data = png_bytes(img)
    path = CORNELL / "wall.png"
    write_if_changed(path, data)
    back = mpimg.imread(path)  # float32 in [0, 1]
    assert back.shape == (1024, 1024, 3), back.shape
    assert np.array_equal(np.round(back * 255).astype(np.uint8), img)
    lin = srgb_to_linear(back)
    print(f"          wall.png linear albedo in [{lin.min():.3f}, {lin.max():.3f}]")
    assert 0.04 < lin.min() and lin.max() < 0.86
    assert len(data) < 600_000, len(data)


# ----------------------------------------------------------------------------------------------
# glTF scene
# ----------------------------------------------------------------------------------------------

def draw_checker(ax):
    S, n = 256, 8
    s = S / n
    a, b = c8("#c8beaa"), c8("#5a6e8c")
    for i in range(n):
        for j in range(n):
            ax.add_patch(Rectangle((j * s, i * s), s, s, color=a if (i + j) % 2 == 0 else b, lw=0))
    # Orientation marks: a red "F" in the top-left tile pair and a yellow disc bottom right.
    red = c8("#c84646")
    ax.add_patch(Rectangle((6, 6), 8, 52, color=red, lw=0))
    ax.add_patch(Rectangle((6, 6), 40, 8, color=red, lw=0))
    ax.add_patch(Rectangle((6, 28), 28, 8, color=red, lw=0))
    ax.add_patch(Circle((S - s / 2, S - s / 2), s / 3, color=c8("#dcc850"), lw=0))
    ax.text(S / 2, S / 2, "glTF", fontsize=26, weight="bold", family="DejaVu Sans", ha="center", va="center",
            color=c8("#e6dcc8"),
            bbox=dict(boxstyle="round,pad=0.2", fc=c8("#7a4a40"), ec="none"))


def quat_axis_angle(axis, degrees):
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    h = math.radians(degrees) / 2
    return [float(a[0] * math.sin(h)), float(a[1] * math.sin(h)), float(a[2] * math.sin(h)), float(math.cos(h))]


def quat_to_matrix(q):
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quat_look_at(eye, target, up=(0.0, 1.0, 0.0)):
    """Rotation taking the camera's local -Z to (target - eye) and local +Y towards up."""
    f = np.asarray(target, float) - np.asarray(eye, float)
    zc = -f / np.linalg.norm(f)
    xc = np.cross(up, zc)
    xc /= np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    m = np.stack([xc, yc, zc], axis=1)  # columns: local axes in world space
    tr = np.trace(m)
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:  # not needed for the camera below; kept simple on purpose
        raise ValueError("look-at rotation too close to 180 degrees")
    return [float(v) for v in q]


def quad_mesh(size_u, size_v, uv_repeat=1.0):
    """A quad in the xz plane (y = 0) facing +y, centred at the origin. uv: u along +x, v along +z
    (glTF's v = 0 is the first image row, which thus lies at the far -z edge)."""
    hu, hv = size_u / 2, size_v / 2
    pos = np.array([[-hu, 0, -hv], [-hu, 0, hv], [hu, 0, hv], [hu, 0, -hv]], np.float32)
    nrm = np.tile(np.array([0, 1, 0], np.float32), (4, 1))
    uv = np.array([[0, 0], [0, 1], [1, 1], [1, 0]], np.float32) * np.float32(uv_repeat)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)  # counter-clockwise seen from +y
    return pos, nrm, uv, idx


def cube_mesh():
    """The cube [-0.5, 0.5]^3 with 24 vertices, flat outward normals and a full uv square per face."""
    faces = [((1, 0, 0), (0, 0, -1), (0, 1, 0)), ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
             ((0, 1, 0), (1, 0, 0), (0, 0, -1)), ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
             ((0, 0, 1), (1, 0, 0), (0, 1, 0)), ((0, 0, -1), (-1, 0, 0), (0, 1, 0))]
    pos, nrm, uv, idx = [], [], [], []
    for n, a, b in faces:
        n, a, b = (np.array(v, np.float64) for v in (n, a, b))
        assert np.allclose(np.cross(a, b), n)
        base = len(pos)
        for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            pos.append(0.5 * (n + cu * a + cv * b))
            nrm.append(n)
            uv.append(((cu + 1) / 2, (1 - cv) / 2))
        idx += [base + i for i in (0, 1, 2, 0, 2, 3)]
    return (np.array(pos, np.float32), np.array(nrm, np.float32), np.array(uv, np.float32),
            np.array(idx, np.uint16))


class GltfBuilder:
    def __init__(self):
        self.bin = bytearray()
        self.doc = {"bufferViews": [], "accessors": []}

    def _view(self, data, target):
        while len(self.bin) % 4:
            self.bin.append(0)
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data),
                                        "target": target})
        self.bin += data
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, array, kind):
        array = np.ascontiguousarray(array)
        if kind == "indices":
            assert array.dtype in (np.uint16, np.uint32) and array.ndim == 1
            view = self._view(array.astype(array.dtype.newbyteorder("<")).tobytes(), 34963)  # ELEMENT_ARRAY_BUFFER
            acc = {"bufferView": view, "byteOffset": 0, "componentType": 5123 if array.dtype == np.uint16 else 5125,
                   "count": int(array.size), "type": "SCALAR"}
        else:
            assert array.dtype == np.float32 and array.ndim == 2 and array.shape[1] in (2, 3)
            view = self._view(array.astype("<f4").tobytes(), 34962)  # ARRAY_BUFFER
            acc = {"bufferView": view, "byteOffset": 0, "componentType": 5126, "count": int(array.shape[0]),
                   "type": "VEC%d" % array.shape[1]}
            if kind == "POSITION":  # required by the spec; exact float32 values
                acc["min"] = [float(v) for v in array.min(axis=0)]
                acc["max"] = [float(v) for v in array.max(axis=0)]
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def primitive(self, mesh, material):
        pos, nrm, uv, idx = mesh
        return {"attributes": {"POSITION": self.accessor(pos, "POSITION"), "NORMAL": self.accessor(nrm, "NORMAL"),
                               "TEXCOORD_0": self.accessor(uv, "TEXCOORD_0")},
                "indices": self.accessor(idx, "indices"), "material": material, "mode": 4}


def r6(v):
    return [round(float(x), 6) + 0.0 for x in v]  # + 0.0 turns -0.0 into 0.0


def make_gltf():
    checker = render_figure(256, draw_checker)
    write_if_changed(GLTF / "checker.png", png_bytes(checker))

    b = GltfBuilder()
    ground = b.primitive(quad_mesh(8.0, 8.0, uv_repeat=4.0), 0)
    cube = cube_mesh()
    gold = b.primitive(cube, 1)
    plastic = b.primitive(cube, 2)
    light = b.primitive(quad_mesh(1.0, 1.0), 3)

    eye, target = [0.0, 2.4, 5.6], [0.0, 0.5, -0.4]
    cam_q = quat_look_at(eye, target)
    doc = {
        "asset": {"version": "2.0", "generator": "backlight scenes/make_assets.py",
                  "extras": {"note": "Generated by scenes/make_assets.py; do not edit by hand."}},
        "scene": 0,
        "scenes": [{"name": "scene", "nodes": [0, 1, 4, 5]}],
        "nodes": [
            {"name": "ground", "mesh": 0},
            {"name": "objects", "translation": [0.0, 0.0, -0.5], "children": [2, 3]},
            {"name": "gold_cube", "mesh": 1, "translation": [-0.9, 0.5, 0.0],
             "rotation": r6(quat_axis_angle([0, 1, 0], 30.0))},
            {"name": "plastic_box", "mesh": 2, "translation": [0.9, 0.7, 0.3],
             "rotation": r6(quat_axis_angle([0, 1, 0], -20.0)), "scale": [0.8, 1.4, 0.8]},
            # The light quad faces +y in its mesh; the node turns it upside down (180 degrees about
            # x), scales it to 2.5 x 2.5 and lifts it to y = 3.2, so it emits downwards.
            {"name": "light", "mesh": 3, "translation": [0.0, 3.2, 0.0],
             "rotation": [1.0, 0.0, 0.0, 0.0], "scale": [2.5, 1.0, 2.5]},
            {"name": "camera", "camera": 0, "translation": eye, "rotation": r6(cam_q)},
        ],
        "cameras": [{"name": "camera", "type": "perspective",
                     "perspective": {"yfov": round(math.radians(40.0), 6), "aspectRatio": 4 / 3,
                                     "znear": 0.05, "zfar": 100.0}}],
        "meshes": [{"name": "ground", "primitives": [ground]},
                   {"name": "gold_cube", "primitives": [gold]},
                   {"name": "plastic_box", "primitives": [plastic]},
                   {"name": "light", "primitives": [light]}],
        "materials": [
            {"name": "ground",
             "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                      "metallicFactor": 0.0, "roughnessFactor": 0.9}},
            {"name": "gold",
             "pbrMetallicRoughness": {"baseColorFactor": [1.0, 0.78, 0.34, 1.0], "metallicFactor": 1.0,
                                      "roughnessFactor": 0.3}},
            {"name": "blue_plastic",
             "pbrMetallicRoughness": {"baseColorFactor": [0.1, 0.3, 0.8, 1.0], "metallicFactor": 0.0,
                                      "roughnessFactor": 0.5}},
            {"name": "lamp",
             "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0,
                                      "roughnessFactor": 1.0},
             "emissiveFactor": [1.0, 1.0, 1.0],
             "extras": {"note": "backlight uses emissiveFactor (times KHR_materials_emissive_strength, "
                                "absent here) as the emitted radiance, as is; glTF caps emissiveFactor at 1."}},
        ],
        "textures": [{"sampler": 0, "source": 0}],
        "images": [{"uri": "checker.png", "mimeType": "image/png"}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}],
        "buffers": [{"uri": "scene.bin", "byteLength": 0}],
    }
    while len(b.bin) % 4:
        b.bin.append(0)
    doc["bufferViews"] = b.doc["bufferViews"]
    doc["accessors"] = b.doc["accessors"]
    doc["buffers"][0]["byteLength"] = len(b.bin)
    text = json.dumps(doc, indent=1) + "\n"
    write_if_changed(GLTF / "scene.bin", bytes(b.bin))
    write_if_changed(GLTF / "scene.gltf", text.encode())
    check_gltf(GLTF / "scene.gltf")


# ----------------------------------------------------------------------------------------------
# glTF read-back checks
# ----------------------------------------------------------------------------------------------

COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
DTYPES = {5121: np.dtype("u1"), 5123: np.dtype("<u2"), 5125: np.dtype("<u4"), 5126: np.dtype("<f4")}


def check_gltf(path):
    doc = json.loads(path.read_text())
    assert doc["asset"]["version"] == "2.0"
    buffers = []
    for buf in doc["buffers"]:
        data = (path.parent / buf["uri"]).read_bytes()
        assert len(data) == buf["byteLength"], (len(data), buf["byteLength"])
        buffers.append(data)
    for v in doc["bufferViews"]:
        assert v["byteOffset"] % 4 == 0 and v["byteLength"] > 0
        assert v["byteOffset"] + v["byteLength"] <= len(buffers[v["buffer"]])
        assert v["target"] in (34962, 34963) and "byteStride" not in v

    def read(ai):
        a = doc["accessors"][ai]
        v = doc["bufferViews"][a["bufferView"]]
        dt, nc = DTYPES[a["componentType"]], COMPONENTS[a["type"]]
        off = v["byteOffset"] + a.get("byteOffset", 0)
        assert off % dt.itemsize == 0
        assert a.get("byteOffset", 0) + a["count"] * nc * dt.itemsize <= v["byteLength"]
        arr = np.frombuffer(buffers[v["buffer"]], dtype=dt, count=a["count"] * nc, offset=off)
        return a, v, arr.reshape(a["count"], nc) if nc > 1 else arr

    for mesh in doc["meshes"]:
        for p in mesh["primitives"]:
            assert p.get("mode", 4) == 4
            apos, vpos, pos = read(p["attributes"]["POSITION"])
            assert apos["componentType"] == 5126 and apos["type"] == "VEC3" and vpos["target"] == 34962
            assert apos["min"] == [float(x) for x in pos.min(axis=0)]
            assert apos["max"] == [float(x) for x in pos.max(axis=0)]
            anrm, vnrm, nrm = read(p["attributes"]["NORMAL"])
            auv, vuv, uv = read(p["attributes"]["TEXCOORD_0"])
            assert anrm["componentType"] == 5126 and anrm["type"] == "VEC3" and vnrm["target"] == 34962
            assert auv["componentType"] == 5126 and auv["type"] == "VEC2" and vuv["target"] == 34962
            assert len(pos) == len(nrm) == len(uv)
            assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
            aidx, vidx, idx = read(p["indices"])
            assert aidx["componentType"] in (5123, 5125) and aidx["type"] == "SCALAR" and vidx["target"] == 34963
            assert aidx["count"] % 3 == 0 and idx.max() < len(pos)
            tri = idx.reshape(-1, 3)
            p0, p1, p2 = (pos[tri[:, k]].astype(np.float64) for k in range(3))
            geo = np.cross(p1 - p0, p2 - p0)  # counter-clockwise winding = front face
            assert np.all(np.einsum("ij,ij->i", geo, nrm[tri[:, 0]]) > 0), mesh["name"]
            assert 0 <= p["material"] < len(doc["materials"])

    for m in doc["materials"]:
        assert m.get("name")
        assert all(0 <= x <= 1 for x in m.get("emissiveFactor", [0, 0, 0]))
    for t in doc["textures"]:
        img = doc["images"][t["source"]]
        arr = mpimg.imread(path.parent / img["uri"])
        assert arr.ndim == 3 and arr.shape[2] == 3, arr.shape

    # World transforms: the light must face down, the camera must look at the objects.
    def local(node):
        m = np.eye(4)
        s = np.diag(node.get("scale", [1, 1, 1]))
        m[:3, :3] = quat_to_matrix(node.get("rotation", [0, 0, 0, 1])) @ s
        m[:3, 3] = node.get("translation", [0, 0, 0])
        return m

    world = {}

    def visit(i, parent):
        world[i] = parent @ local(doc["nodes"][i])
        for c in doc["nodes"][i].get("children", []):
            visit(c, world[i])

    for i in doc["scenes"][doc["scene"]]["nodes"]:
        visit(i, np.eye(4))
    assert sorted(world) == list(range(len(doc["nodes"]))), "every node must be reachable exactly once"
    for i, node in enumerate(doc["nodes"]):
        if "rotation" in node:
            assert abs(np.linalg.norm(node["rotation"]) - 1) < 1e-6
        if node.get("name") == "light":
            n = np.linalg.inv(world[i][:3, :3]).T @ np.array([0, 1, 0])
            assert np.allclose(n / np.linalg.norm(n), [0, -1, 0]), n
        if "camera" in node:
            fwd = world[i][:3, :3] @ np.array([0, 0, -1.0])
            to_obj = np.array([0.0, 0.5, -0.4]) - world[i][:3, 3]
            assert np.dot(fwd, to_obj / np.linalg.norm(to_obj)) > 0.9999, fwd
            assert (world[i][:3, :3] @ np.array([0, 1.0, 0]))[1] > 0.9
    print(f"          {path.name}: {len(doc['accessors'])} accessors, {len(doc['bufferViews'])} buffer views, "
          f"{len(doc['meshes'])} meshes, {len(doc['materials'])} materials: OK")


SMOKE = SCENES / "smoke"
# The plume's two holes: centre (x, y, z) and radius in the grid's unit cube (tools/smoke_regions
# measures the recovered density's error in and around them).
SMOKE_HOLES = ((0.55, 0.45, 0.5, 0.09), (0.42, 0.7, 0.45, 0.08))


def smoke_density(n=128, seed=3):
    """A rising, swirling plume of wispy blobs with two holes, zero near the box faces.

    Values in [0, 1] on voxel centres, returned as rho[iz, iy, ix] (the .vol order)."""
    rng = np.random.default_rng(seed)
    c = (np.arange(n, dtype=np.float64) + 0.5) / n
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    rho = np.zeros((n, n, n))
    for _ in range(50):  # blobs along a helix, rising in y
        t = rng.uniform(0.0, 1.0)
        cx = 0.5 + 0.2 * np.sin(7.0 * t + 1.0) + rng.normal(0, 0.03)
        cz = 0.5 + 0.2 * np.cos(6.0 * t) + rng.normal(0, 0.03)
        cy = 0.15 + 0.7 * t
        r = 0.06 + 0.05 * rng.uniform()
        rho += rng.uniform(0.4, 1.0) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / (2 * r * r))
    # Wisps: modulation by a few random low-frequency waves (smooth enough for a dozen views to
    # determine: the optimization job recovers it).
    wave = np.zeros_like(rho)
    for _ in range(4):
        k = rng.uniform(1.0, 3.0, size=3) * rng.choice([-1.0, 1.0], size=3)
        wave += np.sin(2 * np.pi * (k[0] * x + k[1] * y + k[2] * z) + rng.uniform(0, 2 * np.pi))
    rho *= np.clip(0.6 + 0.2 * wave, 0.0, None)
    # Holes.
    for hx, hy, hz, hr in SMOKE_HOLES:
        rho[(x - hx) ** 2 + (y - hy) ** 2 + (z - hz) ** 2 < hr * hr] = 0.0
    rho *= np.clip((0.47 - np.sqrt((x - 0.5) ** 2 + (z - 0.5) ** 2)) / 0.05, 0.0, 1.0)  # fade at the sides
    rho *= np.clip((0.97 - y) / 0.05, 0.0, 1.0) * np.clip((y - 0.03) / 0.05, 0.0, 1.0)
    rho = np.clip(rho / np.percentile(rho[rho > 0], 99.5), 0.0, 1.0)
    return rho.astype(np.float32)


def vol_bytes(rho, bbox):
    nz, ny, nx = rho.shape
    header = b"VOL" + bytes([3]) + struct.pack("<5i", 1, nx, ny, nz, 1) + struct.pack("<6f", *bbox)
    return header + rho.astype("<f4").tobytes()


def pfm_bytes(rgb):
    """Portable float map, rows from the bottom up, little endian."""
    h, w, _ = rgb.shape
    return f"PF\n{w} {h}\n-1.0\n".encode() + np.ascontiguousarray(rgb[::-1].astype("<f4")).tobytes()


def sky(width=64, height=32):
    """Blue above, white at the horizon, dim ground; latitude-longitude, row 0 = up."""
    v = (np.arange(height) + 0.5) / height
    elevation = (0.5 - v) * np.pi  # +pi/2 at the top row
    up = np.clip(np.sin(elevation), 0.0, 1.0)[:, None]
    rgb = np.zeros((height, width, 3))
    for ch, (horizon, zenith) in enumerate(((0.9, 0.25), (0.95, 0.45), (1.0, 0.9))):
        rgb[..., ch] = horizon + (zenith - horizon) * up
    rgb[elevation < 0] *= 0.2
    return rgb


def make_smoke():
    SMOKE.mkdir(exist_ok=True)
    rho = smoke_density()
    data = vol_bytes(rho, (-1.0, 0.0, -1.0, 1.0, 2.0, 1.0))
    write_if_changed(SMOKE / "density.vol", data)
    back = np.frombuffer((SMOKE / "density.vol").read_bytes()[48:], dtype="<f4")
    assert back.size == rho.size and np.array_equal(back, rho.ravel()), "density.vol read-back mismatch"
    write_if_changed(SMOKE / "sky.pfm", pfm_bytes(sky()))
    write_vdb_if_changed(SMOKE / "density.vdb", rho, (-1.0, 0.0, -1.0, 1.0, 2.0, 1.0))


def write_vdb_if_changed(path, rho, bbox):
    """rho[iz, iy, ix] as an OpenVDB float grid named "density" whose voxel centres sit where the
    .vol's do: index (i, j, k) = (x, y, z) at bbox_min + (index + 0.5) · voxel size. Voxels equal
    to the background, 0, stay inactive (they read as 0); the two corner voxels are made active so
    that the active bounding box, from which readers take the grid's extent, is the whole 128³ box.
    OpenVDB stamps each file with a random UUID, so "unchanged" compares the grid read back, not
    the bytes."""
    import pyopenvdb as vdb  # python3-openvdb (tools/deps)

    nz, ny, nx = rho.shape
    size = [(bbox[3 + a] - bbox[a]) / n for a, n in enumerate((nx, ny, nz))]
    assert max(size) - min(size) < 1e-12, "OpenVDB voxels are cubes"
    h = size[0]

    def read(p):
        g = vdb.read(str(p), "density")
        lo, hi = g.evalActiveVoxelBoundingBox()
        out = np.zeros((hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1), dtype=np.float32)
        g.copyToArray(out, ijk=lo)
        centre = g.transform.indexToWorld((0, 0, 0))
        return lo, out.transpose(2, 1, 0), centre, g.transform.voxelSize()

    want_centre = tuple(bbox[a] + 0.5 * h for a in range(3))

    def matches(p):
        lo, values, centre, voxel = read(p)
        return (tuple(lo) == (0, 0, 0) and values.shape == rho.shape and np.array_equal(values, rho)
                and np.allclose(centre, want_centre, rtol=0, atol=1e-12)
                and np.allclose(voxel, (h, h, h), rtol=0, atol=1e-15))

    def existing_matches():
        try:
            return path.exists() and matches(path)
        except (KeyError, RuntimeError, IOError):  # another grid name, or not a VDB file: rewrite it
            return False

    if existing_matches():
        print(f"unchanged {path.relative_to(SCENES.parent)} (grid read back)")
        return
    grid = vdb.FloatGrid(0.0)
    grid.name = "density"
    grid.copyFromArray(np.ascontiguousarray(rho.transpose(2, 1, 0)), ijk=(0, 0, 0), tolerance=0.0)
    acc = grid.getAccessor()
    for ijk in ((0, 0, 0), (nx - 1, ny - 1, nz - 1)):
        acc.setActiveState(ijk, True)
    grid.transform = vdb.createLinearTransform(
        [[h, 0, 0, 0], [0, h, 0, 0], [0, 0, h, 0], [want_centre[0], want_centre[1], want_centre[2], 1]])
    tmp = path.with_name(path.name + ".tmp")
    vdb.write(str(tmp), grids=[grid])
    assert matches(tmp), f"{tmp}: read-back mismatch"
    tmp.replace(path)
    print(f"wrote     {path.relative_to(SCENES.parent)} ({path.stat().st_size} bytes)")


DEFORM = SCENES / "deform"


def icosphere(subdivisions):
    """Unit icosphere: vertices on the sphere, triangles counter-clockwise seen from outside."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
             (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    verts = [np.array(v, dtype=np.float64) / np.linalg.norm(v) for v in verts]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(subdivisions):
        midpoint = {}

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in midpoint:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                midpoint[key] = len(verts) - 1
            return midpoint[key]

        new_faces = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new_faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new_faces
    return np.array(verts), np.array(faces, dtype=np.int64)


def blob(p):
    """The deformation target: each unit-sphere vertex moved radially onto a smooth blob (bumps of
    radius ~0.5, a dent, and an elongation), at most ~0.35 from the sphere."""
    def bump(centre, width):
        c = np.array(centre, dtype=np.float64)
        c /= np.linalg.norm(c)
        return np.exp(-np.sum((p - c) ** 2, axis=1) / width)

    r = (1.0 + 0.35 * bump((0.6, 0.7, 0.3), 0.25) + 0.3 * bump((-0.7, -0.2, 0.6), 0.2)
         + 0.25 * bump((0.1, -0.8, -0.6), 0.3) - 0.15 * bump((-0.3, 0.5, -0.8), 0.3))
    q = p * r[:, None]
    return q * np.array([1.12, 0.9, 1.0])


def ply_bytes(verts, faces):
    head = ("ply\nformat ascii 1.0\ncomment scenes/make_assets.py\n"
            f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
            f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    body = "".join(f"{v[0]:.6f} {v[1]:.6f} {v[2]:.6f}\n" for v in verts)
    body += "".join(f"3 {a} {b} {c}\n" for a, b, c in faces)
    return (head + body).encode()


def make_deform():
    DEFORM.mkdir(exist_ok=True)
    verts, faces = icosphere(4)
    write_if_changed(DEFORM / "sphere.ply", ply_bytes(verts, faces))
    write_if_changed(DEFORM / "target.ply", ply_bytes(blob(verts), faces))
    for name, expect in (("sphere.ply", verts), ("target.ply", blob(verts))):
        text = (DEFORM / name).read_text().split("end_header\n")[1].splitlines()
        back = np.array([[float(x) for x in line.split()] for line in text[:len(expect)]])
        assert np.abs(back - expect).max() < 1e-5, name + " read-back mismatch"


def main():
    if sys.argv[1:] == ["--smoke"]:
        make_smoke()
        return 0
    if sys.argv[1:]:
        print("usage: scenes/make_assets.py [--smoke]", file=sys.stderr)
        return 2
    make_wall()
    make_gltf()
    make_smoke()
    make_deform()
    return 0


if __name__ == "__main__":
    sys.exit(main())
