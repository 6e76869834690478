// Mitsuba 3 XML scenes and OBJ/PLY meshes: the Mitsuba Cornell box written as XML with its
// shapes in OBJ and PLY files renders like scenes/mitsuba-cornell/scene.json; mesh readers
// (polygons, negative OBJ indices, ASCII and big-endian PLY); every unsupported construct is an
// error naming the plugin and its line.
#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "engine/core/errors.h"
#include "engine/integrators/render.h"
#include "engine/io/image_io.h"
#include "engine/scene/mesh_io.h"
#include "engine/scene/scene_load.h"
#include "test_scenes.h"

using namespace bl;
using nlohmann::json;

namespace {

std::string cornell_json() { return std::string(BL_SOURCE_DIR) + "/scenes/mitsuba-cornell/scene.json"; }

void write_obj(const std::string& path, const json& shape) {
  std::ofstream f(path);
  char line[160];
  const bool normals = shape.contains("normals"), uvs = shape.contains("uvs");
  for (const auto& p : shape["positions"]) {
    std::snprintf(line, sizeof line, "v %.9g %.9g %.9g\n", p[0].get<double>(), p[1].get<double>(), p[2].get<double>());
    f << line;
  }
  if (normals)
    for (const auto& n : shape["normals"]) {
      std::snprintf(line, sizeof line, "vn %.9g %.9g %.9g\n", n[0].get<double>(), n[1].get<double>(),
                    n[2].get<double>());
      f << line;
    }
  if (uvs)
    for (const auto& t : shape["uvs"]) {
      std::snprintf(line, sizeof line, "vt %.9g %.9g\n", t[0].get<double>(), t[1].get<double>());
      f << line;
    }
  for (const auto& tri : shape["indices"]) {
    f << "f";
    for (const auto& i : tri) {
      const long k = i.get<long>() + 1;
      f << " " << k;
      if (uvs || normals) f << "/" << (uvs ? std::to_string(k) : "") << (normals ? "/" + std::to_string(k) : "");
    }
    f << "\n";
  }
}

// Binary big-endian PLY (the byte order that needs swapping on this machine).
void write_ply(const std::string& path, const json& shape) {
  std::ofstream f(path, std::ios::binary);
  const bool normals = shape.contains("normals"), uvs = shape.contains("uvs");
  f << "ply\nformat binary_big_endian 1.0\ncomment written by test_xml\nelement vertex " << shape["positions"].size()
    << "\nproperty float x\nproperty float y\nproperty float z\n";
  if (normals) f << "property float nx\nproperty float ny\nproperty float nz\n";
  if (uvs) f << "property float u\nproperty float v\n";
  f << "element face " << shape["indices"].size() << "\nproperty list uchar int vertex_indices\nend_header\n";
  auto put = [&](auto v) {
    unsigned char b[sizeof v];
    std::memcpy(b, &v, sizeof v);
    if (std::endian::native == std::endian::little)
      for (size_t i = 0; i < sizeof v / 2; ++i) std::swap(b[i], b[sizeof v - 1 - i]);
    f.write(reinterpret_cast<const char*>(b), sizeof v);
  };
  for (size_t i = 0; i < shape["positions"].size(); ++i) {
    for (int c = 0; c < 3; ++c) put(shape["positions"][i][size_t(c)].get<float>());
    if (normals)
      for (int c = 0; c < 3; ++c) put(shape["normals"][i][size_t(c)].get<float>());
    if (uvs)
      for (int c = 0; c < 2; ++c) put(shape["uvs"][i][size_t(c)].get<float>());
  }
  for (const auto& tri : shape["indices"]) {
    put(uint8_t(3));
    for (const auto& i : tri) put(int32_t(i.get<int>()));
  }
}

std::string rgb(const json& v) {
  char b[96];
  std::snprintf(b, sizeof b, "%.9g, %.9g, %.9g", v[0].get<double>(), v[1].get<double>(), v[2].get<double>());
  return b;
}

// A JSON scene's mesh as a Mitsuba <shape>: the mesh written to DIR as an OBJ or a big-endian PLY
// file, its material a <ref>, its interior medium a <ref name="interior">, its area emitter nested.
std::string shape_xml(const std::string& dir, const json& shape, bool obj) {
  const std::string file = shape["name"].get<std::string>() + (obj ? ".obj" : ".ply");
  if (obj)
    write_obj(dir + "/" + file, shape);
  else
    write_ply(dir + "/" + file, shape);
  std::ostringstream x;
  x << "  <shape type=\"" << (obj ? "obj" : "ply") << "\" id=\"" << shape["name"].get<std::string>() << "\">\n"
    << "    <string name=\"filename\" value=\"" << file << "\"/>\n"
    << (obj ? "    <boolean name=\"flip_tex_coords\" value=\"false\"/>\n" : "") << "    <ref id=\""
    << shape["material"].get<std::string>() << "\"/>\n";
  if (shape.contains("interior"))
    x << "    <ref name=\"interior\" id=\"" << shape["interior"].get<std::string>() << "\"/>\n";
  if (shape.contains("emitter"))
    x << "    <emitter type=\"area\"><rgb name=\"radiance\" value=\"" << rgb(shape["emitter"]["radiance"])
      << "\"/></emitter>\n";
  x << "  </shape>\n";
  return x.str();
}

// An XML scene and its JSON counterpart render alike: Σ |a − b| / Σ b < 1e-4 (an all-black
// reference fails), at `side`² pixels (0: the scenes' own size), `spp`, the same seed. The camera
// frame goes through lookat → matrix → origin/target/up, which may round its last bits
// differently: hence 1e-4 of the mean brightness rather than bit for bit. Returns the image.
Image check_renders_alike(Scene& xml, Scene& ref, int side, int spp, uint64_t seed) {
  for (Scene* s : {&xml, &ref})
    if (side > 0) {
      s->cameras[0].width = s->cameras[0].height = side;
      s->cameras[0].update();
    }
  const Image a = render(xml, {0, spp, seed, false}), b = render(ref, {0, spp, seed, false});
  double diff = 0, sum = 0;
  size_t differing = 0;
  for (size_t i = 0; i < a.data.size(); ++i) {
    diff += std::abs(double(a.data[i]) - b.data[i]);
    sum += b.data[i];
    differing += a.data[i] != b.data[i];
  }
  const double rel = sum > 0 ? diff / sum : 1.0;
  INFO("pixel values that differ: " << differing << " of " << a.data.size() << ", mean |diff| / mean " << rel);
  CHECK(rel < 1e-4);
  return a;
}

// scenes/mitsuba-cornell as a Mitsuba XML file: shapes alternate between OBJ and PLY files.
std::string write_cornell_xml(const std::string& dir) {
  std::ifstream in(cornell_json());
  const json s = json::parse(in);
  const json& cam = s["cameras"][0];
  std::ostringstream x;
  x << "<scene version=\"3.0.0\">\n  <default name=\"spp\" value=\"" << s["integrator"]["spp"] << "\"/>\n"
    << "  <integrator type=\"path\">\n    <integer name=\"max_depth\" value=\"" << s["integrator"]["max_depth"]
    << "\"/>\n    <integer name=\"rr_depth\" value=\"" << s["integrator"]["rr_depth"] << "\"/>\n  </integrator>\n"
    << "  <sensor type=\"perspective\">\n    <float name=\"fov\" value=\"" << cam["fov"].get<double>() << "\"/>\n"
    << "    <string name=\"fov_axis\" value=\"x\"/>\n    <float name=\"near_clip\" value=\""
    << cam["near_clip"].get<double>() << "\"/>\n    <transform name=\"to_world\">\n      <lookat origin=\""
    << rgb(cam["origin"]) << "\" target=\"" << rgb(cam["target"]) << "\" up=\"" << rgb(cam["up"]) << "\"/>\n"
    << "    </transform>\n    <sampler type=\"independent\"><integer name=\"sample_count\" value=\"$spp\"/></sampler>\n"
    << "    <film type=\"hdrfilm\">\n      <integer name=\"width\" value=\"" << cam["resolution"][0] << "\"/>\n"
    << "      <integer name=\"height\" value=\"" << cam["resolution"][1] << "\"/>\n"
    << "      <rfilter type=\"box\"/>\n    </film>\n  </sensor>\n";
  for (auto it = s["materials"].begin(); it != s["materials"].end(); ++it)
    x << "  <bsdf type=\"diffuse\" id=\"" << it.key() << "\">\n    <rgb name=\"reflectance\" value=\""
      << rgb(it.value()["albedo"]) << "\"/>\n  </bsdf>\n";
  int k = 0;
  for (const auto& shape : s["shapes"]) x << shape_xml(dir, shape, k++ % 2 == 0);
  x << "</scene>\n";
  std::ofstream(dir + "/cornell.xml") << x.str();
  return dir + "/cornell.xml";
}

std::string write(const std::string& dir, const std::string& name, const std::string& text) {
  std::ofstream(dir + "/" + name) << text;
  return dir + "/" + name;
}

std::string error_of(const std::string& path) {
  try {
    load_scene(path);
  } catch (const InputError& e) {
    return e.what();
  }
  return "(no error)";
}

struct ErrorCase {
  std::string body, message;
};
// Each body, inside <scene version="3.0.0">, is a one-line error that starts with the file's path and
// contains the message.
void check_errors(const std::string& dir, const std::vector<ErrorCase>& cases) {
  for (const ErrorCase& c : cases) {
    INFO(c.body);
    const std::string path = write(dir, "scene.xml", "<scene version=\"3.0.0\">\n" + c.body + "</scene>\n");
    const std::string e = error_of(path);
    CHECK_THAT(e, Catch::Contains(c.message) && Catch::StartsWith(path + ": "));
    CHECK(e.find('\n') == std::string::npos);
  }
}

}  // namespace

TEST_CASE("the Mitsuba Cornell box as XML with OBJ and PLY meshes renders like its JSON scene", "[xml]") {
  const std::string dir = test::temp_dir("xml-cornell");
  auto xml = load_scene(write_cornell_xml(dir));
  auto ref = load_scene(cornell_json());
  REQUIRE(xml->meshes.size() == ref->meshes.size());
  CHECK(xml->settings.spp == ref->settings.spp);
  CHECK(xml->settings.max_depth == ref->settings.max_depth);
  check_renders_alike(*xml, *ref, 48, 16, 3);
}

TEST_CASE("OBJ and PLY readers: polygons, relative indices, ASCII PLY, flipped texture coordinates", "[xml][mesh]") {
  const std::string dir = test::temp_dir("xml-mesh");
  // A quad with negative (relative) indices and a pentagon: fans of 2 and 3 triangles.
  write(dir, "poly.obj",
        "# comment\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "f -4/-4 -3/-3 -2/-2 -1/-1\nv 2 0 0\nv 3 0 0\nv 3 1 0\nv 2.5 2 0\nv 2 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0.5 1\nvt 0 1\nf 5/5 6/6 7/7 8/8 9/9\n");
  Mesh m = read_obj(dir + "/poly.obj", true);
  CHECK(m.triangle_count() == 5);
  CHECK(m.positions.size() == 9);
  REQUIRE(m.uvs.size() == 9);
  CHECK(m.uvs[0].y == 1.f);  // v flipped (Mitsuba's default)
  CHECK(read_obj(dir + "/poly.obj", false).uvs[0].y == 0.f);
  write(dir, "quad.ply",
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "property float s\nproperty float t\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n"
        "0 0 0 0 0\n1 0 0 1 0\n1 1 0 1 1\n0 1 0 0 1\n4 0 1 2 3\n");
  Mesh q = read_ply(dir + "/quad.ply");
  CHECK(q.triangle_count() == 2);
  REQUIRE(q.uvs.size() == 4);
  CHECK(q.uvs[2].x == 1.f);
  CHECK(q.normals.empty());
  // The same through a JSON scene: obj/ply shape types.
  write(dir, "scene.json",
        R"({"cameras": [{"origin": [0.5, 0.5, 3], "target": [0.5, 0.5, 0], "fov": 60, "resolution": [16, 16]}],
  "materials": {"m": {"type": "diffuse", "albedo": 0.5}},
  "shapes": [{"name": "a", "type": "obj", "file": "poly.obj", "material": "m"},
             {"name": "b", "type": "ply", "file": "quad.ply", "material": "m", "transform": {"translate": [0, 0, -1]}},
             {"name": "c", "type": "sphere", "material": "m", "transform": {"scale": 0.2}}],
  "environment": {"type": "constant", "radiance": [1, 1, 1]}})");
  auto scene = load_scene(dir + "/scene.json");
  CHECK(scene->meshes.size() == 3);
  CHECK(scene->meshes[2].triangle_count() == 64 * 32 * 2 - 2 * 64);
}

TEST_CASE("OBJ comments end any line", "[xml][mesh]") {
  // '#' to the end of a line is a comment after data too, as files written by hand put them: a
  // face with one was refused ("'#' is not a face vertex").
  const std::string dir = test::temp_dir("xml-obj-comments");
  write(dir, "commented.obj",
        "# whole line\r\no quad # named\nv 0 0 0 # origin\nv 1 0 0#x\nv 1 1 0\nv 0 1 0\nvt 0 0 # uv\n"
        "vn 0 0 1 # up\ng # no name\nusemtl m # ignored\nf 1 2 3 # tri\nf 1 3 4# another\nf 1//1 2//1 3//1 #\n"
        "# f 7 8 9\n");
  const Mesh m = read_obj(dir + "/commented.obj", true);
  CHECK(m.triangle_count() == 3);
  CHECK(m.positions.size() == 4);
  CHECK(m.positions[1].x == 1.f);
}

TEST_CASE("bad meshes are one-line errors naming the file", "[xml][mesh]") {
  const std::string dir = test::temp_dir("xml-badmesh");
  const std::pair<const char*, const char*> cases[] = {
      {"v 0 0 0\nv 1 0 0\nf 1 2 7\n", "face refers to vertex 7"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//2 3//1\n", "face refers to normal 2"},
      {"v 0 0 0\n", "no faces"},
      {"v 1e39 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "NaN or infinite"},
      // tinyobjloader reads these as 0, and wraps an index past 2^31 around to a valid vertex.
      {"v 0 0 0\nv nan -1 0\nv 0 1 0\nf 1 2 3\n", "line 2: 'nan' in a 'v' line is not a finite number"},
      {"v 0 0 0\nv abc -1 0\nv 0 1 0\nf 1 2 3\n", "line 2: 'abc' in a 'v' line is not a finite number"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1x\nf 1 2 3\n", "line 4: '1x' in a 'vn' line is not a finite number"},
      {"v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", "line 2: a 'v' line needs 3 values"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n",
       "line 4: face index 99999999999999999999 is out of range"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3x\n", "line 4: '3x' is not a face vertex"},
      // Faces of one or two vertices: tinyobjloader dropped them with a warning nobody read.
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2\n", "line 5: a face needs at least 3 vertices, not 2"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1\nf 1 2 3\n", "line 4: a face needs at least 3 vertices, not 1"},
      // Behind comments (OBJ comments end any line): the same errors, lines counted with the comments.
      {"# a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 # 3\n", "line 5: a face needs at least 3 vertices, not 2"},
      {"v 0 0 0\r\nv 1 0 # 0\nv 0 1 0\nf 1 2 3\n", "line 2: a 'v' line needs 3 values"},
      {"v 0 0 0 # a\nv 1 0 0\nv 0 1 0\nf 1 2 3x # b\n", "line 4: '3x' is not a face vertex"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7 # past the end\n", "face refers to vertex 7"},
      {"v 0 0 0 # f 1 2 3\n", "no faces"},
  };
  for (const auto& [text, message] : cases) {
    INFO(text);
    write(dir, "bad.obj", text);
    try {
      read_obj(dir + "/bad.obj", true);
      FAIL("no error");
    } catch (const InputError& e) {
      CHECK_THAT(e.what(), Catch::Contains(message) && Catch::Contains("bad.obj"));
    }
  }
  const std::pair<const char*, const char*> plys[] = {
      {"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n", "need x, y and z"},
      {"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
       "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1 0 0 0 1 0 3 0 1 9\n",
       "refers to vertex 9"},
      {"ply\nformat binary_little_endian 1.0\nelement vertex 200000000\nproperty float x\nproperty float y\n"
       "property float z\nend_header\n",
       "larger than the file"},
      {"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
       "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1 0 0\n",
       "'vertex' is larger than the file"},
      {"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
       "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1 0 0 0 1 0\n3 0 1\n",
       "ends early"},
      {"PLY\n", "not a PLY file"},
      // An unsigned stream read took -4 for 2^64 - 4; the count is reported as written.
      {"ply\nformat ascii 1.0\nelement vertex -4\nproperty float x\nproperty float y\nproperty float z\n"
       "end_header\n",
       "malformed PLY element line 'element vertex -4'"},
      {"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
       "element face 1\nproperty list float int vertex_indices\nend_header\n0 0 0 1 0 0 0 1 0\n3 0 1 2\n",
       "PLY list count type 'float' is not an integer type"},
      {"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "no end_header"},
      // A face of fewer than 3 indices was dropped without a word.
      {"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
       "element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1 0 0 0 1 0\n3 0 1 2\n2 0 1\n",
       "PLY face 1 has 2 vertex indices (a face needs at least 3)"},
      {"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
       "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1 0 0 0 1 0\n0\n",
       "PLY face 0 has 0 vertex indices"},
  };
  for (const auto& [text, message] : plys) {
    INFO(text);
    write(dir, "bad.ply", text);
    try {
      read_ply(dir + "/bad.ply");
      FAIL("no error");
    } catch (const InputError& e) {
      CHECK_THAT(e.what(), Catch::Contains(message) && Catch::Contains("bad.ply"));
    }
  }
}

TEST_CASE("unsupported XML constructs are errors naming the plugin and the line", "[xml]") {
  const std::string dir = test::temp_dir("xml-errors");
  write(dir, "quad.obj", "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3 4\n");
  write_image(dir + "/sky.exr", Image(4, 2, 3));
  const std::string sensor =
      "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>"
      "<film type=\"hdrfilm\"><integer name=\"width\" value=\"8\"/><integer name=\"height\" value=\"8\"/>"
      "<rfilter type=\"box\"/></film></sensor>\n";
  const std::string shape = "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/></shape>\n";
  const std::vector<ErrorCase> cases = {
      {sensor + shape + "<bsdf type=\"dielectric\" id=\"glass\"/>\n",
       "line 4: <bsdf type=\"dielectric\">: unsupported bsdf type"},
      {sensor + "<shape type=\"disk\"/>\n", "line 3: <shape type=\"disk\">: unsupported shape type"},
      {sensor + shape + "<emitter type=\"point\"/>\n", "line 4: <emitter type=\"point\">: unsupported emitter"},
      {sensor + shape + "<emitter type=\"envmap\"/>\n", "line 4: <emitter type=\"envmap\">: envmap needs a filename"},
      {sensor + shape +
           "<emitter type=\"envmap\"><string name=\"filename\" value=\"sky.exr\"/><transform name=\"to_world\">"
           "<scale value=\"2\"/></transform></emitter>\n",
       "line 4: <emitter type=\"envmap\"> (scene key 'transform'): must be a rotation"},
      {sensor + shape + "<integrator type=\"direct\"/>\n",
       "line 4: <integrator type=\"direct\">: unsupported integrator"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                "<float name=\"bogus\" value=\"1\"/></shape>\n",
       "line 3: <float name=\"bogus\">: unsupported property of line 3: <shape type=\"obj\">"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"$mesh\"/></shape>\n", "unknown parameter $mesh"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><ref id=\"nope\"/></shape>\n",
       "no element with id 'nope'"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                "<bsdf type=\"roughconductor\"><string name=\"material\" value=\"Au\"/></bsdf></shape>\n",
       "named conductor material 'Au' is not supported"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                "<bsdf type=\"diffuse\"><spectrum name=\"reflectance\" value=\"400:0.1, 700:0.5\"/></bsdf></shape>\n",
       "wavelength-sampled spectra are not supported"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                "<medium type=\"homogeneous\" name=\"inside\"/></shape>\n",
       "line 3: <medium type=\"homogeneous\" name=\"inside\">: a shape's medium is named interior or exterior"},
      {"<sensor type=\"thinlens\"/>\n" + shape, "line 2: <sensor type=\"thinlens\">: unsupported sensor"},
      {shape, "the scene has no <sensor>"},
      {sensor + shape + "<include filename=\"other.xml\"/>\n", "line 4: <include>: unsupported <include>"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><transform name=\"to_world\">"
                "<rotate x=\"1\" angle=\"abc\"/></transform></shape>\n",
       "'abc' is not a finite number"},
      {sensor + shape + "<shape", "malformed XML"},
      // Errors found in the translated scene name the XML element, not the JSON pointer
      // ("/shapes/0 ('shape_0')") of a file the user never wrote.
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><transform name=\"to_world\">"
                "<scale x=\"0\"/></transform></shape>\n",
       "xml: line 3: <shape type=\"obj\"> ('shape_0'): degenerate transform (zero scale)"},
      {sensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                "<bsdf type=\"diffuse\"><rgb name=\"reflectance\" value=\"1.5, 0.5, 0.5\"/></bsdf></shape>\n",
       "xml: line 3: <bsdf type=\"diffuse\"> (scene key 'albedo'): parameter 'bsdf_"},
      {"<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/><float name=\"near_clip\" value=\"-1\"/>"
       "</sensor>\n" +
           shape,
       "xml: line 2: <sensor type=\"perspective\"> (scene key 'near_clip'): value -1 outside"},
      // References that lead back (a stack overflow before) or nest twosided in twosided.
      {sensor + shape + "<bsdf type=\"twosided\" id=\"a\"><ref id=\"a\"/></bsdf>\n",
       "line 4: <bsdf type=\"twosided\">: a twosided bsdf inside a twosided bsdf"},
      {sensor + shape +
           "<bsdf type=\"twosided\" id=\"a\"><ref id=\"b\"/></bsdf>\n"
           "<bsdf type=\"twosided\" id=\"b\"><ref id=\"a\"/></bsdf>\n",
       "a twosided bsdf inside a twosided bsdf"},
  };
  check_errors(dir, cases);
  {  // a chain of 30,000 twosided references: one error at once, not a stack overflow
    std::string chain = sensor + shape;
    for (int i = 0; i < 30000; ++i)
      chain += "<bsdf type=\"twosided\" id=\"b" + std::to_string(i) + "\"><ref id=\"b" + std::to_string(i + 1) +
               "\"/></bsdf>\n";
    chain += "<bsdf type=\"diffuse\" id=\"b30000\"/>\n";
    check_errors(dir, {{chain, "line 5: <bsdf type=\"twosided\">: a twosided bsdf inside a twosided bsdf"}});
  }
  // A harmless attribute is one warning, not an error; defaults substitute.
  const std::string ok = write(dir, "ok.xml",
                               "<scene version=\"3.0.0\"><default name=\"w\" value=\"8\"/>"
                               "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>"
                               "<float name=\"far_clip\" value=\"1000\"/><film type=\"hdrfilm\">"
                               "<integer name=\"width\" value=\"$w\"/><integer name=\"height\" value=\"6\"/>"
                               "<string name=\"pixel_format\" value=\"rgb\"/></film></sensor>" +
                                   shape + "</scene>\n");
  auto scene = load_scene(ok);
  CHECK(scene->cameras[0].width == 8);
  CHECK(scene->cameras[0].height == 6);
}

// A bitmap texture's wrap_mode: Mitsuba's repeat, mirror and clamp (mirror was refused).
TEST_CASE("Mitsuba bitmap wrap modes", "[xml]") {
  const std::string dir = test::temp_dir("xml-wrap");
  write(dir, "quad.obj", "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n");
  Image tex(4, 4, 3);
  for (size_t i = 0; i < tex.data.size(); ++i) tex.data[i] = 0.1f + 0.05f * float(i % 13);
  write_image(dir + "/tex.exr", tex);
  for (const auto& [mode, wrap] :
       {std::pair{"repeat", Wrap::Repeat}, {"mirror", Wrap::Mirror}, {"clamp", Wrap::Clamp}}) {
    CAPTURE(mode);
    const std::string path = write(
        dir, "wrap.xml",
        std::string("<scene version=\"3.0.0\"><sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>"
                    "<film type=\"hdrfilm\"><integer name=\"width\" value=\"8\"/><integer name=\"height\" "
                    "value=\"8\"/></film></sensor><shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                    "<bsdf type=\"diffuse\"><texture type=\"bitmap\" name=\"reflectance\"><string name=\"filename\" "
                    "value=\"tex.exr\"/><string name=\"wrap_mode\" value=\"") +
            mode + "\"/></texture></bsdf></shape></scene>\n");
    auto scene = load_scene(path);
    bool found = false;
    for (const Material& m : scene->materials) found = found || (m.albedo.bitmap && m.albedo.wrap == wrap);
    CHECK(found);
  }
}

// An envmap emitter is the environment in Mitsuba's convention (bilinear lookup, u = 0 at −z;
// the lookup itself is tested against Mitsuba's formula in kernels_envmap): scale, identity
// to_world, float files as stored and 8-bit files sRGB-decoded, and the scene renders; a rotating
// to_world orients the map (its translation dropped, as Mitsuba applies to_world to directions).
TEST_CASE("Mitsuba envmap emitters", "[xml]") {
  const std::string dir = test::temp_dir("xml-envmap");
  write(dir, "quad.obj", "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3 4\n");
  Image sky(8, 4, 3);
  for (size_t i = 0; i < sky.data.size(); ++i) sky.data[i] = 0.1f + 0.05f * float(i % 17);
  write_image(dir + "/sky.exr", sky);
  write_image(dir + "/sky.png", sky);
  const std::string head =
      "<scene version=\"3.0.0\"><sensor type=\"perspective\"><float name=\"fov\" value=\"60\"/>"
      "<transform name=\"to_world\"><lookat origin=\"0,0,4\" target=\"0,0,0\" up=\"0,1,0\"/></transform>"
      "<film type=\"hdrfilm\"><integer name=\"width\" value=\"16\"/><integer name=\"height\" value=\"16\"/>"
      "</film></sensor><shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/></shape>";
  for (const char* file : {"sky.exr", "sky.png"}) {
    CAPTURE(file);
    const std::string path =
        write(dir, "env.xml",
              head + "<emitter type=\"envmap\"><string name=\"filename\" value=\"" + file +
                  "\"/><float name=\"scale\" value=\"2.5\"/><transform name=\"to_world\"><scale value=\"1\"/>"
                  "</transform><boolean name=\"mis_compensation\" value=\"false\"/></emitter></scene>\n");
    auto scene = load_scene(path);
    const Environment& env = scene->environment;
    REQUIRE(env.present);
    CHECK(env.is_map);
    CHECK(env.bilinear);
    CHECK(env.scale == 2.5f);
    const Param& p = scene->params[env.param];
    REQUIRE(p.shape == std::vector<int>{4, 8, 3});
    const bool png = std::string(file) == "sky.png";
    for (size_t i = 0; i < p.value.size(); ++i) {
      // The PNG stores sRGB rounded to 1/255; decoded back to linear it is within 0.5/255 × 2.27.
      const float want = sky.data[i];
      CHECK(p.value[i] == Approx(want).margin(png ? 0.5 / 255 * 2.27 : 0.0));
    }
    const Image img = render(*scene, {0, 4, 2, false});
    double sum = 0;
    for (float v : img.data) sum += v;
    CHECK(sum > 0);
    CHECK(!env.rotated);
  }
  const std::string path =
      write(dir, "env_rotated.xml",
            head +
                "<emitter type=\"envmap\"><string name=\"filename\" value=\"sky.exr\"/><transform name=\"to_world\">"
                "<rotate x=\"1\" angle=\"-90\"/><rotate y=\"1\" angle=\"30\"/><translate value=\"5, 0, 0\"/>"
                "</transform></emitter></scene>\n");
  auto scene = load_scene(path);
  const Environment& env = scene->environment;
  REQUIRE(env.rotated);
  const Transform want = Transform::rotate({0, 1, 0}, 30.f) * Transform::rotate({1, 0, 0}, -90.f);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) CHECK(env.rotation[i][j] == Approx(want.m[i][j]).margin(1e-6));
  const Image img = render(*scene, {0, 4, 2, false});
  double sum = 0;
  for (float v : img.data) sum += v;
  CHECK(sum > 0);
}

namespace {

std::string volume_json() { return std::string(BL_SOURCE_DIR) + "/scenes/mitsuba-volume/scene.json"; }

// scenes/mitsuba-volume (the Mitsuba 3 reference's heterogeneous medium in the Cornell room) as a
// Mitsuba XML file: the medium a top-level heterogeneous <medium> whose sigma_t is a gridvolume
// mapped by a translating to_world (Mitsuba ignores the box in the .vol file), the box a null
// bsdf with a <ref name="interior">.
std::string write_volume_xml(const std::string& dir) {
  std::ifstream in(volume_json());
  const json s = json::parse(in);
  const json& cam = s["cameras"][0];
  const json& smoke = s["media"]["smoke"];
  const json& lo = smoke["bbox"]["min"];
  std::ostringstream x;
  x << "<scene version=\"3.0.0\">\n  <integrator type=\"volpath\">\n    <integer name=\"max_depth\" value=\""
    << s["integrator"]["max_depth"] << "\"/>\n    <integer name=\"rr_depth\" value=\"" << s["integrator"]["rr_depth"]
    << "\"/>\n  </integrator>\n  <sensor type=\"perspective\">\n    <float name=\"fov\" value=\""
    << cam["fov"].get<double>() << "\"/>\n    <float name=\"near_clip\" value=\"" << cam["near_clip"].get<double>()
    << "\"/>\n    <transform name=\"to_world\">\n      <lookat origin=\"" << rgb(cam["origin"]) << "\" target=\""
    << rgb(cam["target"]) << "\" up=\"" << rgb(cam["up"]) << "\"/>\n    </transform>\n"
    << "    <film type=\"hdrfilm\"><integer name=\"width\" value=\"256\"/><integer name=\"height\" value=\"256\"/>"
    << "<rfilter type=\"box\"/></film>\n  </sensor>\n"
    << "  <medium type=\"heterogeneous\" id=\"smoke\">\n    <volume name=\"sigma_t\" type=\"gridvolume\">\n"
    << "      <string name=\"filename\" value=\"" << BL_SOURCE_DIR << "/scenes/mitsuba-volume/density.vol\"/>\n"
    << "      <transform name=\"to_world\"><translate value=\"" << rgb(lo) << "\"/></transform>\n    </volume>\n"
    << "    <rgb name=\"albedo\" value=\"" << rgb(smoke["albedo"]) << "\"/>\n    <float name=\"scale\" value=\""
    << smoke["scale"].get<double>() << "\"/>\n    <phase type=\"hg\"><float name=\"g\" value=\""
    << smoke["phase"]["g"].get<double>() << "\"/></phase>\n  </medium>\n";
  for (auto it = s["materials"].begin(); it != s["materials"].end(); ++it) {
    if (it.value()["type"] == "null") {
      x << "  <bsdf type=\"null\" id=\"" << it.key() << "\"/>\n";
      continue;
    }
    x << "  <bsdf type=\"diffuse\" id=\"" << it.key() << "\">\n    <rgb name=\"reflectance\" value=\""
      << rgb(it.value()["albedo"]) << "\"/>\n  </bsdf>\n";
  }
  for (const auto& shape : s["shapes"]) x << shape_xml(dir, shape, true);
  x << "</scene>\n";
  std::ofstream(dir + "/volume.xml") << x.str();
  return dir + "/volume.xml";
}

}  // namespace

TEST_CASE("the Mitsuba volume scene as XML (heterogeneous medium, gridvolume) renders like its JSON scene",
          "[xml][media]") {
  const std::string dir = test::temp_dir("xml-volume");
  auto xml = load_scene(write_volume_xml(dir));
  auto ref = load_scene(volume_json());
  REQUIRE(xml->media.size() == 1);
  REQUIRE(ref->media.size() == 1);
  const Medium &a = xml->media[0], &b = ref->media[0];
  CHECK(a.name == "smoke");
  CHECK(a.grid);
  for (int k = 0; k < 3; ++k) {
    CHECK(a.bbox_min[k] == b.bbox_min[k]);
    CHECK(a.bbox_max[k] == b.bbox_max[k]);
  }
  for (const char* name : {"smoke.density", "smoke.albedo", "smoke.scale", "smoke.g"}) {
    CAPTURE(name);
    const int ha = xml->params.find(name), hb = ref->params.find(name);
    REQUIRE(ha >= 0);
    REQUIRE(hb >= 0);
    CHECK(xml->params[ha].shape == ref->params[hb].shape);
    CHECK(xml->params[ha].value == ref->params[hb].value);
  }
  const int box =
      int(std::find_if(xml->meshes.begin(), xml->meshes.end(), [](const Mesh& m) { return m.name == "medium-box"; }) -
          xml->meshes.begin());
  REQUIRE(box < int(xml->meshes.size()));
  CHECK(xml->meshes[size_t(box)].interior == 0);
  CHECK(xml->meshes[size_t(box)].exterior == -1);
  CHECK(xml->materials[size_t(xml->meshes[size_t(box)].material)].is_null);
  CHECK(xml->settings.max_depth == ref->settings.max_depth);
  check_renders_alike(*xml, *ref, 40, 8, 5);
}

// Homogeneous media: shape interiors and exteriors, a sensor inside one, values as properties or
// constvolumes, Mitsuba's defaults (albedo 0.75, isotropic phase, hg's g 0.8); the same scene as
// JSON renders the same image.
TEST_CASE("Mitsuba homogeneous media: interiors, exteriors, a sensor medium, constvolumes and defaults",
          "[xml][media]") {
  const std::string dir = test::temp_dir("xml-homogeneous");
  const std::string xml_path = write(
      dir, "fog.xml",
      "<scene version=\"3.0.0\">\n"
      "<integrator type=\"volpath\"><integer name=\"max_depth\" value=\"4\"/></integrator>\n"
      "<medium type=\"homogeneous\" id=\"fog\"><float name=\"sigma_t\" value=\"0.05\"/>"
      "<volume name=\"albedo\" type=\"constvolume\"><rgb name=\"value\" value=\"0.2, 0.4, 0.6\"/></volume>"
      "<phase type=\"hg\"><float name=\"g\" value=\"-0.3\"/></phase></medium>\n"
      "<sensor type=\"perspective\"><float name=\"fov\" value=\"50\"/><ref name=\"medium\" id=\"fog\"/>"
      "<transform name=\"to_world\"><lookat origin=\"0, 0, 4\" target=\"0, 0, 0\" up=\"0, 1, 0\"/></transform>"
      "<film type=\"hdrfilm\"><integer name=\"width\" value=\"24\"/><integer name=\"height\" value=\"24\"/>"
      "<rfilter type=\"box\"/></film></sensor>\n"
      "<emitter type=\"constant\"><rgb name=\"radiance\" value=\"1, 0.9, 0.8\"/></emitter>\n"
      "<shape type=\"cube\" id=\"box\"><bsdf type=\"null\"/>"
      "<medium type=\"homogeneous\" name=\"interior\"><rgb name=\"sigma_t\" value=\"2\"/>"
      "<float name=\"scale\" value=\"1.5\"/></medium><ref name=\"exterior\" id=\"fog\"/></shape>\n"
      "<medium type=\"homogeneous\" id=\"haze\"><float name=\"sigma_t\" value=\"0.1\"/><phase type=\"hg\"/></medium>\n"
      "<shape type=\"cube\" id=\"world\"><transform name=\"to_world\"><scale value=\"10\"/></transform>"
      "<bsdf type=\"null\"/><ref name=\"interior\" id=\"fog\"/></shape>\n"
      "<shape type=\"cube\" id=\"far\"><transform name=\"to_world\"><translate z=\"-6\"/></transform>"
      "<bsdf type=\"null\"/><ref name=\"interior\" id=\"haze\"/><ref name=\"exterior\" id=\"fog\"/></shape>\n"
      "</scene>\n");
  auto xml = load_scene(xml_path);
  REQUIRE(xml->media.size() == 3);
  auto medium = [&](const std::string& name) {
    for (size_t i = 0; i < xml->media.size(); ++i)
      if (xml->media[i].name == name) return int(i);
    return -1;
  };
  const int fog = medium("fog"), haze = medium("haze");
  REQUIRE(fog >= 0);
  REQUIRE(haze >= 0);
  const int inner = 3 - fog - haze;  // the anonymous one
  auto value = [&](const std::string& name) {
    const int h = xml->params.find(name);
    REQUIRE(h >= 0);
    return xml->params[h].value;
  };
  const std::string in = xml->media[size_t(inner)].name;
  for (const Medium& m : xml->media) CHECK_FALSE(m.grid);
  CHECK(value("fog.density") == std::vector<float>{0.05f});
  CHECK(value("fog.albedo") == std::vector<float>{0.2f, 0.4f, 0.6f});
  CHECK(value("fog.scale") == std::vector<float>{1.f});
  CHECK(value("fog.g") == std::vector<float>{-0.3f});
  CHECK(value(in + ".density") == std::vector<float>{2.f});
  CHECK(value(in + ".scale") == std::vector<float>{1.5f});
  CHECK(value(in + ".albedo") == std::vector<float>{0.75f, 0.75f, 0.75f});
  CHECK(xml->params.find(in + ".g") < 0);  // isotropic
  CHECK(value("haze.g") == std::vector<float>{0.8f});
  CHECK(xml->cameras[0].medium == fog);
  REQUIRE(xml->meshes.size() == 3);
  for (const Mesh& m : xml->meshes) {
    CAPTURE(m.name);
    CHECK(m.exterior == (m.name == "world" ? -1 : fog));
    CHECK(m.interior == (m.name == "box" ? inner : m.name == "world" ? fog : haze));
  }
  // The same scene written as JSON by hand.
  const std::string json_path = write(dir, "fog.json",
                                      R"({"integrator": {"max_depth": 4},
          "cameras": [{"origin": [0, 0, 4], "target": [0, 0, 0], "up": [0, 1, 0], "fov": 50, "fov_axis": "x",
                       "resolution": [24, 24], "medium": "fog"}],
          "environment": {"type": "constant", "radiance": [1, 0.9, 0.8]},
          "materials": {"null": {"type": "null"}},
          "media": {"fog": {"type": "homogeneous", "density": 0.05, "albedo": [0.2, 0.4, 0.6], "scale": 1,
                            "phase": {"type": "hg", "g": -0.3}},
                    "inner": {"type": "homogeneous", "density": 2, "albedo": 0.75, "scale": 1.5},
                    "haze": {"type": "homogeneous", "density": 0.1, "albedo": 0.75, "phase": {"type": "hg", "g": 0.8}}},
          "shapes": [{"name": "box", "type": "cube", "material": "null", "interior": "inner", "exterior": "fog"},
                     {"name": "far", "type": "cube", "material": "null", "interior": "haze", "exterior": "fog",
                      "transform": {"translate": [0, 0, -6]}},
                     {"name": "world", "type": "cube", "material": "null", "interior": "fog",
                      "transform": {"scale": [10, 10, 10]}}]})");
  auto ref = load_scene(json_path);
  const Image img = check_renders_alike(*xml, *ref, 0, 16, 9);
  double sum = 0;
  for (float v : img.data) sum += v;
  CHECK(sum > 0.05 * double(img.data.size()));  // the environment, seen through the fog
}

TEST_CASE("unsupported or malformed XML media are errors naming the element and the line", "[xml][media]") {
  const std::string dir = test::temp_dir("xml-media-errors");
  write(dir, "quad.obj", "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3 4\n");
  {
    // A 2×2×2 grid in Mitsuba's .vol format.
    std::ofstream f(dir + "/g.vol", std::ios::binary);
    const int32_t header[5] = {1, 2, 2, 2, 1};
    const float box[6] = {0, 0, 0, 1, 1, 1};
    f.write("VOL\x03", 4);
    f.write(reinterpret_cast<const char*>(header), sizeof header);
    f.write(reinterpret_cast<const char*>(box), sizeof box);
    for (int i = 0; i < 8; ++i) {
      const float v = 0.25f * float(i % 3);
      f.write(reinterpret_cast<const char*>(&v), 4);
    }
  }
  const std::string sensor =
      "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>"
      "<film type=\"hdrfilm\"><integer name=\"width\" value=\"8\"/><integer name=\"height\" value=\"8\"/>"
      "<rfilter type=\"box\"/></film></sensor>\n";
  auto shape_with = [](const std::string& medium) {
    return "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><bsdf type=\"null\"/>" + medium +
           "</shape>\n";
  };
  const std::string grid = "<string name=\"filename\" value=\"g.vol\"/>";
  const std::vector<ErrorCase> cases = {
      {sensor + shape_with("<medium type=\"absorbing\" name=\"interior\"/>"),
       "line 3: <medium type=\"absorbing\" name=\"interior\">: unsupported medium type"},
      {sensor + shape_with("<medium type=\"homogeneous\" name=\"interior\"><rgb name=\"sigma_t\" value=\"1, 2, 3\"/>"
                           "</medium>"),
       "<rgb name=\"sigma_t\">: sigma_t must be the same in R, G and B"},
      {sensor + shape_with("<medium type=\"homogeneous\" name=\"interior\">"
                           "<boolean name=\"sample_emitters\" value=\"false\"/></medium>"),
       "sample_emitters false is not supported"},
      {sensor + shape_with("<medium type=\"homogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                           "type=\"gridvolume\">" +
                           grid + "</volume></medium>"),
       "<volume type=\"gridvolume\" name=\"sigma_t\">: a homogeneous medium takes a constant sigma_t"},
      {sensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                           "type=\"gridvolume\">" +
                           grid +
                           "<transform name=\"to_world\"><rotate y=\"1\" angle=\"30\"/></transform></volume></medium>"),
       "a gridvolume's to_world must be a scale and a translation"},
      {sensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                           "type=\"gridvolume\">" +
                           grid + "<transform name=\"to_world\"><scale x=\"-1\"/></transform></volume></medium>"),
       "a gridvolume's to_world must scale by positive factors"},
      {sensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                           "type=\"gridvolume\">" +
                           grid + "<string name=\"filter_type\" value=\"nearest\"/></volume></medium>"),
       "filter_type 'nearest' is not supported"},
      {sensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                           "type=\"gridvolume\">" +
                           grid + "</volume><volume name=\"albedo\" type=\"gridvolume\">" + grid +
                           "<transform name=\"to_world\"><scale value=\"2\"/></transform></volume></medium>"),
       "<volume type=\"gridvolume\" name=\"albedo\">: the albedo grid must fill the same box as the sigma_t grid"},
      {sensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"albedo\" "
                           "type=\"gridvolume\">" +
                           grid + "</volume></medium>"),
       "an albedo grid needs a sigma_t grid"},
      {sensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"emission\" "
                           "type=\"constvolume\"/></medium>"),
       "unexpected volume 'emission' in a medium"},
      {sensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                           "type=\"gridvolume\"/></medium>"),
       "gridvolume needs a filename"},
      {sensor + shape_with("<medium type=\"homogeneous\" name=\"interior\"><phase type=\"rayleigh\"/></medium>"),
       "line 3: <phase type=\"rayleigh\">: unsupported phase function"},
      {sensor + shape_with("<medium type=\"homogeneous\" name=\"interior\"><float name=\"density\" value=\"1\"/>"
                           "</medium>"),
       "<float name=\"density\">: unsupported property of"},
      {"<integrator type=\"volpath\"/>\n" + sensor +
           shape_with("<medium type=\"homogeneous\" name=\"interior\"><float name=\"sigma_t\" value=\"-1\"/>"
                      "</medium>"),
       "density"},
      {sensor + "<medium type=\"homogeneous\"/>\n" + shape_with(""),
       "line 3: <medium type=\"homogeneous\">: a "
       "top-level <medium> needs an id"},
      {"<medium type=\"homogeneous\" id=\"m\"/>\n<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>"
       "<ref name=\"outside\" id=\"m\"/></sensor>\n" +
           shape_with(""),
       "line 3: <ref name=\"outside\">: a sensor's medium is named medium"},
  };
  check_errors(dir, cases);
  // A grid file that is not there: the error names it.
  const std::string path =
      write(dir, "missing.xml",
            "<scene version=\"3.0.0\">\n" + sensor +
                shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                           "type=\"gridvolume\"><string name=\"filename\" value=\"nowhere.vol\"/></volume></medium>") +
                "</scene>\n");
  const std::string e = error_of(path);
  CHECK_THAT(e, Catch::Contains("nowhere.vol"));
  CHECK(e.find('\n') == std::string::npos);
}

// ---- Mitsuba 3 semantics found missing by the XML import audit ------------------------------

namespace {

const std::string kSensor =
    "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>"
    "<film type=\"hdrfilm\"><integer name=\"width\" value=\"8\"/><integer name=\"height\" value=\"8\"/>"
    "<rfilter type=\"box\"/></film></sensor>\n";

// A scene from a body inside <scene version="3.0.0">, written into DIR and loaded.
std::unique_ptr<Scene> load_body(const std::string& dir, const std::string& body) {
  return load_scene(write(dir, "scene.xml", "<scene version=\"3.0.0\">\n" + body + "</scene>\n"));
}

std::vector<float> elements(const Vec3f& v) { return {v.x, v.y, v.z}; }
std::vector<float> elements(const Vec2f& v) { return {v.x, v.y}; }

std::string quad_obj(const std::string& dir) {
  write(dir, "quad.obj", "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\n");
  return "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/></shape>\n";
}

}  // namespace

// Mitsuba's path and volpath default to max_depth −1 (C++ MonteCarloIntegrator), prb and
// prbvolpath to 6 (Python ADIntegrator); rr_depth 5; rr_depth 0 and a second integrator are errors
// there; a scene without an integrator is rendered as path.
TEST_CASE("Mitsuba integrator defaults: max_depth -1 for path/volpath, 6 for prb/prbvolpath", "[xml]") {
  const std::string dir = test::temp_dir("xml-integrator");
  const std::string shape = quad_obj(dir);
  for (const auto& [type, depth] : {std::pair{"path", -1}, {"volpath", -1}, {"prb", 6}, {"prbvolpath", 6}}) {
    CAPTURE(type);
    auto scene = load_body(dir, kSensor + shape + "<integrator type=\"" + type + "\"/>\n");
    CHECK(scene->settings.max_depth == depth);
    CHECK(scene->settings.rr_depth == 5);
  }
  CHECK(load_body(dir, kSensor + shape)->settings.max_depth == -1);
  auto given = load_body(dir, kSensor + shape +
                                  "<integrator type=\"prb\"><integer name=\"max_depth\" value=\"3\"/>"
                                  "<integer name=\"rr_depth\" value=\"1\"/></integrator>\n");
  CHECK(given->settings.max_depth == 3);
  CHECK(given->settings.rr_depth == 1);
  check_errors(dir,
               {{kSensor + shape + "<integrator type=\"path\"><integer name=\"rr_depth\" value=\"0\"/></integrator>\n",
                 "line 4: <integer name=\"rr_depth\">: rr_depth must be at least 1 in Mitsuba 3"},
                {kSensor + shape + "<integrator type=\"path\"/>\n<integrator type=\"volpath\"/>\n",
                 "line 5: <integrator type=\"volpath\">: a second <integrator>"}});
}

// Mitsuba's path and prb integrators ignore media: a scene with media needs volpath or prbvolpath.
TEST_CASE("media under Mitsuba's path or prb integrator are errors", "[xml][media]") {
  const std::string dir = test::temp_dir("xml-path-media");
  quad_obj(dir);
  const std::string fog_shape =
      "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><bsdf type=\"null\"/>"
      "<medium type=\"homogeneous\" name=\"interior\"><float name=\"sigma_t\" value=\"1\"/></medium></shape>\n";
  const std::string sensor_fog =
      "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/><medium type=\"homogeneous\" name=\"medium\">"
      "<float name=\"sigma_t\" value=\"1\"/></medium></sensor>\n"
      "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/></shape>\n";
  check_errors(dir, {{"<integrator type=\"path\"/>\n" + kSensor + fog_shape,
                      "line 2: <integrator type=\"path\">: integrator 'path' ignores media in Mitsuba 3: use volpath "
                      "or prbvolpath"},
                     {"<integrator type=\"prb\"/>\n" + sensor_fog, "integrator 'prb' ignores media in Mitsuba 3"},
                     {kSensor + fog_shape, "no <integrator>, so integrator 'path' ignores media"}});
  for (const char* type : {"volpath", "prbvolpath"}) {
    CAPTURE(type);
    CHECK(load_body(dir, std::string("<integrator type=\"") + type + "\"/>\n" + kSensor + fog_shape)->media.size() ==
          1);
  }
}

// A sensor's to_world: Mitsuba refuses scale factors; a mirror it renders mirrored, which backlight's
// camera (origin, target, up) cannot: both are errors, not an unmirrored lookat.
TEST_CASE("mirroring or scaling sensor transforms are errors", "[xml]") {
  const std::string dir = test::temp_dir("xml-sensor-transform");
  const std::string shape = quad_obj(dir);
  auto sensor = [](const std::string& steps) {
    return "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/><transform name=\"to_world\">" + steps +
           "</transform></sensor>\n";
  };
  const std::string look = "<lookat origin=\"0, 0, 3\" target=\"0, 0, 0\" up=\"0, 1, 0\"/>";
  check_errors(dir, {{sensor("<scale x=\"-1\"/>" + look) + shape,
                      "line 2: <transform name=\"to_world\">: a mirroring sensor to_world (negative determinant)"},
                     {sensor("<scale value=\"2\"/>" + look) + shape, "sensor to_world with scale factors or shear"},
                     {sensor(look + "<scale y=\"1.01\"/>") + shape, "sensor to_world with scale factors or shear"},
                     {sensor("<matrix value=\"1 0 0 0  0 1 0 0  0 0 1 0  0 0 1 1\"/>") + shape,
                      "a sensor to_world must be affine"}});
  // A rotation and a translation are fine (within Mitsuba's 1e-3 tolerance).
  auto scene = load_body(dir, sensor("<rotate y=\"1\" angle=\"30\"/><translate x=\"1\"/>") + shape);
  CHECK(scene->cameras[0].origin.x == Approx(1.0));
}

// Mitsuba's <lookat> without `up`, or with a zero one, takes the first vector of
// coordinate_system(direction) (Duff et al. 2017): backlight's Frame::s, not +y.
TEST_CASE("a lookat without up uses Mitsuba's coordinate_system", "[xml]") {
  const std::string dir = test::temp_dir("xml-lookat");
  const std::string shape = quad_obj(dir);
  const Vec3f origins[] = {{0, 0, 3}, {0, 0, -3}, {2, 1, 3}, {-1, 4, -2}, {3, 0.5f, 0}};
  for (const Vec3f& o : origins)
    for (const char* up : {"", " up=\"0, 0, 0\""}) {
      CAPTURE(o.x, o.y, o.z, up);
      char look[160];
      std::snprintf(look, sizeof look, "<lookat origin=\"%g, %g, %g\" target=\"0, 0, 0\"%s/>", o.x, o.y, o.z, up);
      auto scene = load_body(dir,
                             "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>"
                             "<transform name=\"to_world\">" +
                                 std::string(look) + "</transform></sensor>\n" + shape);
      const Camera& cam = scene->cameras[0];
      // Unit and ⟂ the direction: the camera's up. (target − origin, as the parser computes it:
      // −o would make a zero z negative, which the basis reads as a different sign.)
      const Vec3f expected = Frame(normalize(Vec3f(0.f) - o)).s;
      CHECK(cam.true_up.x == Approx(expected.x).margin(1e-5));
      CHECK(cam.true_up.y == Approx(expected.y).margin(1e-5));
      CHECK(cam.true_up.z == Approx(expected.z).margin(1e-5));
    }
  // Looking down −z, Mitsuba's up is +x (the image turned a quarter from a +y up).
  auto scene = load_body(dir,
                         "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/><transform "
                         "name=\"to_world\"><lookat origin=\"0, 0, 3\" target=\"0, 0, 0\"/></transform>"
                         "</sensor>\n" +
                             shape);
  CHECK(scene->cameras[0].true_up.x == Approx(1.0));
}

// Mitsuba's cube (shapes/cube.cpp, v3.0 to 3.9): four vertices per face, the face's normal, uv
// (0, 1), (1, 1), (1, 0), (0, 0) in vertex order, triangles {4s, 4s+1, 4s+2} and {4s+3, 4s, 4s+2}.
TEST_CASE("a Mitsuba cube has Mitsuba's vertices, normals and uvs", "[xml]") {
  const std::string dir = test::temp_dir("xml-cube");
  auto scene = load_body(dir, kSensor + "<shape type=\"cube\"/>\n");
  REQUIRE(scene->meshes.size() == 1);
  const Mesh& m = scene->meshes[0];
  // Mitsuba's table, written out.
  const float positions[24][3] = {{1, -1, -1}, {1, -1, 1},   {-1, -1, 1}, {-1, -1, -1}, {1, 1, -1},   {-1, 1, -1},
                                  {-1, 1, 1},  {1, 1, 1},    {1, -1, -1}, {1, 1, -1},   {1, 1, 1},    {1, -1, 1},
                                  {1, -1, 1},  {1, 1, 1},    {-1, 1, 1},  {-1, -1, 1},  {-1, -1, 1},  {-1, 1, 1},
                                  {-1, 1, -1}, {-1, -1, -1}, {1, 1, -1},  {1, -1, -1},  {-1, -1, -1}, {-1, 1, -1}};
  const float normals[6][3] = {{0, -1, 0}, {0, 1, 0}, {1, 0, 0}, {0, 0, 1}, {-1, 0, 0}, {0, 0, -1}};
  const float uvs[4][2] = {{0, 1}, {1, 1}, {1, 0}, {0, 0}};
  REQUIRE(m.vertex_count() == 24);
  REQUIRE(m.triangle_count() == 12);
  REQUIRE(m.uvs.size() == 24);
  REQUIRE(m.normals.size() == 24);
  for (size_t v = 0; v < 24; ++v) {
    CAPTURE(v);
    CHECK(elements(m.positions[v]) == std::vector<float>(positions[v], positions[v] + 3));
    CHECK(elements(m.normals[v]) == std::vector<float>(normals[v / 4], normals[v / 4] + 3));
    CHECK(elements(m.uvs[v]) == std::vector<float>(uvs[v % 4], uvs[v % 4] + 2));
  }
  for (size_t t = 0; t < 12; ++t) {
    const uint32_t s = uint32_t(4 * (t / 2));
    const std::vector<uint32_t> want =
        t % 2 == 0 ? std::vector<uint32_t>{s, s + 1, s + 2} : std::vector<uint32_t>{s + 3, s, s + 2};
    CHECK(std::vector<uint32_t>(m.indices.begin() + long(3 * t), m.indices.begin() + long(3 * t + 3)) == want);
    CHECK(dot(m.face_normals[t], m.normals[4 * (t / 2)]) > 0.99f);  // the winding faces outwards
  }
}

// Mitsuba's sphere: u = φ/2π about +z from +x, v = θ/π from +z (the north pole at v = 0);
// backlight's own sphere has v = 0 at −z. Normals and windings stay outward.
TEST_CASE("a Mitsuba sphere has Mitsuba's uvs", "[xml]") {
  const std::string dir = test::temp_dir("xml-sphere");
  auto scene = load_body(dir, kSensor +
                                  "<shape type=\"sphere\"><point name=\"center\" value=\"1, 2, 3\"/>"
                                  "<float name=\"radius\" value=\"2\"/></shape>\n");
  const Mesh& m = scene->meshes[0];
  const double pi = 3.14159265358979;
  size_t checked = 0;
  for (size_t v = 0; v < m.vertex_count(); ++v) {
    const Vec3f local = (m.positions[v] - Vec3f(1, 2, 3)) * 0.5f;
    CAPTURE(v, local.x, local.y, local.z, m.uvs[v].x, m.uvs[v].y);
    CHECK(m.uvs[v].y == Approx(std::acos(std::clamp(double(local.z), -1.0, 1.0)) / pi).margin(1e-5));
    CHECK(dot(m.normals[v], local) > 0.99f);
    const double r = std::hypot(double(local.x), double(local.y));
    if (r < 1e-3) continue;  // at a pole u is arbitrary
    double u = std::atan2(double(local.y), double(local.x)) / (2 * pi);
    if (u < 0) u += 1;
    // The seam's duplicated column has u = 1 where atan2 gives 0.
    CHECK(std::min(std::abs(m.uvs[v].x - u), std::abs(std::abs(m.uvs[v].x - u) - 1)) < 1e-5);
    ++checked;
  }
  CHECK(checked > 1000);
  for (size_t t = 0; t < m.triangle_count(); ++t) {
    const Vec3f c =
        (m.positions[m.indices[3 * t]] + m.positions[m.indices[3 * t + 1]] + m.positions[m.indices[3 * t + 2]]) *
            (1.f / 3.f) -
        Vec3f(1, 2, 3);
    CHECK(dot(m.face_normals[t], c) > 0.f);
  }
}

// OBJ and PLY files without normals: Mitsuba computes angle-weighted vertex normals (Thürmer and
// Wüthrich) in world space, after to_world, unless face_normals; files with normals keep theirs.
TEST_CASE("obj and ply files without normals get Mitsuba's computed vertex normals", "[xml][mesh]") {
  const std::string dir = test::temp_dir("xml-normals");
  // Two triangles sharing the vertex at the origin: normal +z with a 45° angle there, and
  // normal +x with a 90° angle there; each of the others belongs to one triangle.
  write(dir, "fold.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 4 5\n");
  write(dir, "fold.ply",
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 3 4\n");
  auto shape = [](const char* type, const char* file, const std::string& extra) {
    return std::string("<shape type=\"") + type + "\"><string name=\"filename\" value=\"" + file + "\"/>" + extra +
           "</shape>\n";
  };
  const double pi = 3.14159265358979;
  for (const char* type : {"obj", "ply"}) {
    CAPTURE(type);
    const std::string file = std::string("fold.") + type;
    auto scene = load_body(dir, kSensor + shape(type, file.c_str(), ""));
    const Mesh& m = scene->meshes[0];
    REQUIRE(m.normals.size() == m.vertex_count());
    // At the origin: (π/2 · x̂ + π/4 · ẑ) normalised, not the area or uniform average (1, 0, 1)/√2.
    size_t origin = 0;
    while (elements(m.positions[origin]) != std::vector<float>{0, 0, 0}) ++origin;
    CHECK(m.normals[origin].x == Approx(2 / std::sqrt(5.0)));
    CHECK(m.normals[origin].y == Approx(0.0).margin(1e-6));
    CHECK(m.normals[origin].z == Approx(1 / std::sqrt(5.0)));
    // In world space: scaled by 2 in x the first triangle's angle at the origin is atan(1/2), and
    // the normal is not the object-space one transformed ((1, 0, 1)/√2).
    auto scaled = load_body(
        dir, kSensor + shape(type, file.c_str(), "<transform name=\"to_world\"><scale x=\"2\"/></transform>"));
    const Mesh& s = scaled->meshes[0];
    const double a = std::atan(0.5), len = std::hypot(pi / 2, a);
    CHECK(s.normals[origin].x == Approx(pi / 2 / len));
    CHECK(s.normals[origin].z == Approx(a / len));
    // face_normals: flat shading.
    CHECK(load_body(dir, kSensor + shape(type, file.c_str(), "<boolean name=\"face_normals\" value=\"true\"/>"))
              ->meshes[0]
              .normals.empty());
  }
  // A file's own normals are kept.
  write(dir, "own.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nvn 0.6 0 0.8\nf 1//1 2//1 3//1\n");
  auto own = load_body(dir, kSensor + shape("obj", "own.obj", ""));
  CHECK(own->meshes[0].normals[0].x == Approx(0.6));
  // Computed normals go through the scene inline: past 2^20 vertices that is refused, not done
  // at gigabytes of memory.
  {
    const uint32_t count = (1u << 20) + 1;
    std::ofstream f(dir + "/huge.ply", std::ios::binary);
    f << "ply\nformat binary_little_endian 1.0\nelement vertex " << count
      << "\nproperty float x\nproperty float y\nproperty float z\nelement face 1\n"
         "property list uchar int vertex_indices\nend_header\n";
    std::vector<float> xyz(size_t(count) * 3, 0.f);
    xyz[3] = xyz[7] = 1.f;
    f.write(reinterpret_cast<const char*>(xyz.data()), std::streamsize(xyz.size() * sizeof(float)));
    const unsigned char face[13] = {3, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0};
    f.write(reinterpret_cast<const char*>(face), sizeof face);
  }
  check_errors(dir,
               {{kSensor + shape("ply", "huge.ply", ""),
                 "line 3: <shape type=\"ply\">: 'huge.ply' has no vertex normals and more than 1048576 vertices"}});
  CHECK(load_body(dir, kSensor + shape("ply", "huge.ply", "<boolean name=\"face_normals\" value=\"true\"/>"))
            ->meshes.size() == 1);
}

// Mitsuba's plastics: nonlinear is refused (it changes the colour; it was ignored with a warning);
// named indices of refraction are Mitsuba's table; sample_visible (a sampling choice) is accepted.
TEST_CASE("Mitsuba plastic and microfacet properties", "[xml]") {
  const std::string dir = test::temp_dir("xml-plastic");
  const std::string shape_open = "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>";
  quad_obj(dir);
  check_errors(dir, {{kSensor + shape_open +
                          "<bsdf type=\"plastic\"><boolean name=\"nonlinear\" value=\"true\"/>"
                          "</bsdf></shape>\n",
                      "line 3: <boolean name=\"nonlinear\">: nonlinear true"},
                     {kSensor + shape_open +
                          "<bsdf type=\"roughplastic\"><string name=\"int_ior\" value=\"glass\"/>"
                          "</bsdf></shape>\n",
                      "unknown index of refraction 'glass' (a <float>, or one of Mitsuba's names: vacuum, helium"}});
  auto scene =
      load_body(dir, kSensor + shape_open +
                         "<bsdf type=\"roughplastic\"><string name=\"int_ior\" value=\"BK7\"/>"
                         "<string name=\"ext_ior\" value=\"water\"/><boolean name=\"nonlinear\" "
                         "value=\"false\"/><boolean name=\"sample_visible\" value=\"false\"/></bsdf></shape>\n");
  CHECK(scene->materials.back().ior == Approx(1.5046 / 1.333));
  CHECK(load_body(dir, kSensor + shape_open +
                           "<bsdf type=\"roughconductor\"><boolean name=\"sample_visible\" value=\"true\"/></bsdf>"
                           "</shape>\n")
            ->materials.size() == 1);
}

// A heterogeneous medium with a constant sigma_t exists, in Mitsuba, only inside the unit cube
// (through the volume's to_world), not wherever its shapes reach.
TEST_CASE("a heterogeneous medium with a constant sigma_t is an error", "[xml][media]") {
  const std::string dir = test::temp_dir("xml-heterogeneous-constant");
  quad_obj(dir);
  auto shape_with = [](const std::string& medium) {
    return "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><bsdf type=\"null\"/>" + medium +
           "</shape>\n";
  };
  const std::string volpath = "<integrator type=\"volpath\"/>\n";
  check_errors(dir, {{volpath + kSensor +
                          shape_with("<medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                                     "type=\"constvolume\"><float name=\"value\" value=\"2\"/></volume></medium>"),
                      "line 4: <volume type=\"constvolume\" name=\"sigma_t\">: a heterogeneous medium with a "
                      "constant sigma_t fills only the unit cube"},
                     {volpath + kSensor +
                          shape_with("<medium type=\"heterogeneous\" name=\"interior\"><float name=\"sigma_t\" "
                                     "value=\"2\"/></medium>"),
                      "a heterogeneous medium with a constant sigma_t"},
                     {volpath + kSensor + shape_with("<medium type=\"heterogeneous\" name=\"interior\"/>"),
                      "line 4: <medium type=\"heterogeneous\" name=\"interior\">: a heterogeneous medium with a "
                      "constant sigma_t"}});
}

// Mitsuba ends camera rays at far_clip (default 1e4) along the view axis; backlight does not. A
// far_clip that something in the scene reaches is an error; one nothing reaches, a warning.
TEST_CASE("a far_clip that could clip the scene is an error", "[xml]") {
  const std::string dir = test::temp_dir("xml-far-clip");
  quad_obj(dir);
  auto sensor = [](const std::string& extra) {
    return "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>" + extra +
           "<transform name=\"to_world\"><lookat origin=\"0, 0, -5\" target=\"0, 0, 0\" up=\"0, 1, 0\"/>"
           "</transform></sensor>\n";
  };
  auto quad_at = [](double z) {
    return "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><transform name=\"to_world\">"
           "<translate z=\"" +
           std::to_string(z) + "\"/></transform></shape>\n";
  };
  check_errors(dir,
               {{sensor("<float name=\"far_clip\" value=\"4\"/>") + quad_at(0),
                 "line 2: <float name=\"far_clip\">: far_clip 4 clips shape 'shape_0' (at depth 5)"},
                {sensor("") + quad_at(2e4),
                 "line 2: <sensor type=\"perspective\">: Mitsuba's default far_clip 10000 clips shape 'shape_0'"},
                {sensor("<float name=\"far_clip\" value=\"0.001\"/>") + quad_at(0), "far_clip must exceed near_clip"},
                // A medium that may reach past every shape: thin enough to be seen beyond far_clip.
                {"<integrator type=\"volpath\"/>\n" +
                     sensor("<medium type=\"homogeneous\" name=\"medium\"><float name=\"sigma_t\" "
                            "value=\"0.001\"/></medium>") +
                     quad_at(0),
                 "Mitsuba's default far_clip 10000 ends camera rays inside medium"}});
  CHECK(load_body(dir, sensor("<float name=\"far_clip\" value=\"6\"/>") + quad_at(0))->meshes.size() == 1);
  CHECK(load_body(dir, sensor("") + quad_at(9000))->meshes.size() == 1);
  CHECK(load_body(dir, "<integrator type=\"volpath\"/>\n" +
                           sensor("<medium type=\"homogeneous\" name=\"medium\"><float name=\"sigma_t\" "
                                  "value=\"0.05\"/></medium>") +
                           quad_at(0))
            ->media.size() == 1);
}

// One of each where Mitsuba takes one: an area emitter per shape, a film, a sampler per sensor, an
// rfilter per film (the second used to win silently).
TEST_CASE("duplicate emitters, films, samplers and rfilters are errors", "[xml]") {
  const std::string dir = test::temp_dir("xml-duplicates");
  const std::string shape = quad_obj(dir);
  const std::string film = "<film type=\"hdrfilm\"><integer name=\"width\" value=\"8\"/></film>";
  const std::string sampler = "<sampler type=\"independent\"/>";
  auto sensor = [](const std::string& inside) {
    return "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>" + inside + "</sensor>\n";
  };
  check_errors(dir, {{kSensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><emitter "
                                "type=\"area\"/>\n<emitter type=\"area\"><rgb name=\"radiance\" value=\"7\"/>"
                                "</emitter></shape>\n",
                      "line 4: <emitter type=\"area\">: a shape with two emitters"},
                     {sensor(film + film) + shape, "<film type=\"hdrfilm\">: a second <film>"},
                     {sensor(sampler + sampler) + shape, "<sampler type=\"independent\">: a second <sampler>"},
                     {sensor("<film type=\"hdrfilm\"><rfilter type=\"box\"/><rfilter type=\"tent\"/></film>") + shape,
                      "<rfilter type=\"tent\">: a second <rfilter>"}});
}

// Reconstruction filters: Mitsuba's box takes no properties; the others keep their own ones
// (they are rendered as a box, with a warning); anything else is an error.
TEST_CASE("rfilter properties are checked", "[xml]") {
  const std::string dir = test::temp_dir("xml-rfilter");
  const std::string shape = quad_obj(dir);
  auto sensor = [](const std::string& filter) {
    return "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/><film type=\"hdrfilm\">" + filter +
           "</film></sensor>\n";
  };
  check_errors(dir, {{sensor("<rfilter type=\"box\"><float name=\"radius\" value=\"3\"/></rfilter>") + shape,
                      "line 2: <float name=\"radius\">: unsupported property of line 2: <rfilter type=\"box\">"},
                     {sensor("<rfilter type=\"gaussian\"><float name=\"radius\" value=\"3\"/></rfilter>") + shape,
                      "unsupported property of line 2: <rfilter type=\"gaussian\">"},
                     {sensor("<rfilter type=\"gaussian\"><float name=\"stddev\" value=\"abc\"/></rfilter>") + shape,
                      "'abc' is not a finite number"},
                     {sensor("<rfilter type=\"sinc\"/>") + shape, "<rfilter type=\"sinc\">: unsupported rfilter"}});
  for (const char* filter :
       {"<rfilter type=\"gaussian\"><float name=\"stddev\" value=\"0.3\"/></rfilter>",
        "<rfilter type=\"tent\"><float name=\"radius\" value=\"2\"/></rfilter>",
        "<rfilter type=\"mitchell\"><float name=\"B\" value=\"0.3\"/><float name=\"C\" value=\"0.3\"/></rfilter>",
        "<rfilter type=\"lanczos\"><integer name=\"lobes\" value=\"2\"/></rfilter>",
        "<rfilter type=\"catmullrom\"/>"}) {
    CAPTURE(filter);
    CHECK(load_body(dir, sensor(filter) + shape)->meshes.size() == 1);
  }
}

// Bitmap textures: nested objects are errors (they were ignored), nearest filtering is an error
// (it was rendered bilinear with a warning).
TEST_CASE("bitmap texture children and nearest filtering are errors", "[xml]") {
  const std::string dir = test::temp_dir("xml-bitmap");
  quad_obj(dir);
  Image tex(2, 2, 3);
  write_image(dir + "/tex.exr", tex);
  auto with_texture = [](const std::string& inside) {
    return kSensor +
           "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><bsdf type=\"diffuse\">"
           "<texture type=\"bitmap\" name=\"reflectance\"><string name=\"filename\" value=\"tex.exr\"/>" +
           inside + "</texture></bsdf></shape>\n";
  };
  check_errors(dir, {{with_texture("<texture type=\"checkerboard\" name=\"foo\"/>"),
                      "line 3: <texture type=\"checkerboard\" name=\"foo\">: unexpected element in a bitmap texture"},
                     {with_texture("<string name=\"filter_type\" value=\"nearest\"/>"),
                      "<string name=\"filter_type\">: filter_type 'nearest' is not supported"},
                     {with_texture("<string name=\"filter_type\" value=\"cubic\"/>"), "unknown filter_type 'cubic'"}});
  CHECK(load_body(dir, with_texture("<string name=\"filter_type\" value=\"bilinear\"/>"))->meshes.size() == 1);
}

// Mitsuba's default sampler takes 4 samples per pixel (it was backlight's 16); sensors that ask
// for different counts are an error (backlight has one per scene).
TEST_CASE("the default sample count is Mitsuba's 4", "[xml]") {
  const std::string dir = test::temp_dir("xml-spp");
  const std::string shape = quad_obj(dir);
  auto sensor = [](const std::string& inside) {
    return "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>" + inside + "</sensor>\n";
  };
  CHECK(load_body(dir, sensor("") + shape)->settings.spp == 4);
  CHECK(load_body(dir, sensor("<sampler type=\"independent\"/>") + shape)->settings.spp == 4);
  auto given = load_body(dir, sensor("<sampler type=\"independent\"><integer name=\"sample_count\" value=\"9\"/>"
                                     "<integer name=\"seed\" value=\"3\"/></sampler>") +
                                  shape);
  CHECK(given->settings.spp == 9);
  CHECK(given->settings.seed == 3);
  check_errors(dir,
               {{sensor("<sampler type=\"independent\"><integer name=\"sample_count\" value=\"9\"/></sampler>") +
                     sensor("") + shape,
                 "line 3: <sensor type=\"perspective\">: sensors with different sample counts are not supported"}});
}

// The nesting limit counts elements only: '<' and '>' inside attribute values, comments and CDATA
// are not nesting (70 of them were "nested deeper than 64"), while real nesting still is.
TEST_CASE("the XML nesting limit counts elements, not markup inside values or comments", "[xml]") {
  const std::string dir = test::temp_dir("xml-depth");
  const std::string shape = quad_obj(dir);
  std::string quoted, comments, cdata, single;
  for (int i = 0; i < 70; ++i) {
    quoted += "<default name=\"d" + std::to_string(i) + "\" value=\"a>b\"/>\n";
    single += "<default name=\"s" + std::to_string(i) + "\" value='x/><y'/>\n";
    comments += "<!-- <shape type=\"obj\"> disabled -->\n";
    cdata += "<![CDATA[ <shape> ]]>\n";
  }
  CHECK(load_body(dir, kSensor + quoted + single + comments + shape)->meshes.size() == 1);
  CHECK(load_body(dir,
                  kSensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>" + cdata + "</shape>\n")
            ->meshes.size() == 1);
  std::string deep = kSensor + shape;
  for (int i = 0; i < 65; ++i) deep += "<a x=\"/>\">";
  for (int i = 0; i < 65; ++i) deep += "</a>";
  check_errors(dir, {{deep + "\n", "elements nested deeper than 64"}});
}

// A file named by a filename property that is not there: the error names the XML file, the line
// and the element (it named only the missing file).
TEST_CASE("missing files name the XML element that refers to them", "[xml]") {
  const std::string dir = test::temp_dir("xml-missing");
  const std::string shape = quad_obj(dir);
  auto file = [](const std::string& name) { return "<string name=\"filename\" value=\"" + name + "\"/>"; };
  check_errors(dir,
               {{kSensor + "<shape type=\"obj\">" + file("nope.obj") + "</shape>\n",
                 "line 3: <string name=\"filename\">: file 'nope.obj' not found"},
                {kSensor + "<shape type=\"ply\">" + file("sub/nope.ply") + "</shape>\n",
                 "line 3: <string name=\"filename\">: file 'sub/nope.ply' not found"},
                {kSensor + "<shape type=\"obj\">" + file("quad.obj") +
                     "<bsdf type=\"diffuse\"><texture type=\"bitmap\" name=\"reflectance\">" + file("nope.png") +
                     "</texture></bsdf></shape>\n",
                 "line 3: <string name=\"filename\">: file 'nope.png' not found"},
                {kSensor + shape + "<emitter type=\"envmap\">" + file("nope.exr") + "</emitter>\n",
                 "line 4: <string name=\"filename\">: file 'nope.exr' not found"},
                {"<integrator type=\"volpath\"/>\n" + kSensor + "<shape type=\"obj\">" + file("quad.obj") +
                     "<bsdf type=\"null\"/><medium type=\"heterogeneous\" name=\"interior\"><volume name=\"sigma_t\" "
                     "type=\"gridvolume\">" +
                     file("nope.vol") + "</volume></medium></shape>\n",
                 "line 4: <string name=\"filename\">: file 'nope.vol' not found"},
                {kSensor + "<shape type=\"obj\">" + file(".") + "</shape>\n", "'.' is not a regular file"}});
}

// Mitsuba's ids are global: an object declared inside another can be referenced elsewhere.
TEST_CASE("ids declared on nested elements can be referenced", "[xml]") {
  const std::string dir = test::temp_dir("xml-nested-id");
  quad_obj(dir);
  auto scene = load_body(dir, kSensor +
                                  "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                                  "<bsdf type=\"diffuse\" id=\"red\"><rgb name=\"reflectance\" value=\"0.8, 0, 0\"/>"
                                  "</bsdf></shape>\n"
                                  "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/><ref id=\"red\"/>"
                                  "</shape>\n");
  REQUIRE(scene->meshes.size() == 2);
  CHECK(scene->meshes[0].material == scene->meshes[1].material);
  CHECK(scene->materials[size_t(scene->meshes[1].material)].name == "red");
  check_errors(dir, {{kSensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                                "<bsdf type=\"diffuse\" id=\"a\"/></shape>\n<bsdf type=\"diffuse\" id=\"a\"/>\n",
                      "line 4: <bsdf type=\"diffuse\">: duplicate id 'a'"}});
}

// Values Mitsuba reads that were refused: booleans in any case, fov_axis in any case; spectra from
// files or of a plugin type are errors saying so.
TEST_CASE("Mitsuba's case-insensitive values and unsupported spectra", "[xml]") {
  const std::string dir = test::temp_dir("xml-values");
  const std::string shape = quad_obj(dir);
  auto flipped = load_body(dir, kSensor +
                                    "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                                    "<boolean name=\"flip_normals\" value=\"True\"/></shape>\n");
  CHECK(flipped->meshes[0].normals[0].z == -1.f);
  auto axis = load_body(dir,
                        "<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/><string "
                        "name=\"fov_axis\" value=\"Y\"/></sensor>\n" +
                            shape);
  CHECK(axis->cameras[0].fov_axis == Camera::FovAxis::Y);
  check_errors(dir, {{kSensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                                "<bsdf type=\"diffuse\"><spectrum name=\"reflectance\" filename=\"a.spd\"/></bsdf>"
                                "</shape>\n",
                      "<spectrum name=\"reflectance\">: spectra read from files are not supported"},
                     {kSensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                                "<emitter type=\"area\"><spectrum name=\"radiance\" type=\"blackbody\">"
                                "<float name=\"temperature\" value=\"3000\"/></spectrum></emitter></shape>\n",
                      "spectrum type 'blackbody' is not supported"},
                     {kSensor + "<shape type=\"obj\"><string name=\"filename\" value=\"quad.obj\"/>"
                                "<boolean name=\"flip_normals\" value=\"yes\"/></shape>\n",
                      "expected true or false"}});
}
