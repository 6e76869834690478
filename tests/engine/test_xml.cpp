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
           "<rotate y=\"1\" angle=\"90\"/></transform></emitter>\n",
       "envmap to_world must be the identity"},
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
// to_world, float files as stored and 8-bit files sRGB-decoded, and the scene renders.
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
  }
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
      {sensor + shape_with("<medium type=\"homogeneous\" name=\"interior\"><float name=\"sigma_t\" value=\"-1\"/>"
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
