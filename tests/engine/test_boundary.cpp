// The boundary (visibility) terms of geometry gradients (edge sampling,
// engine/integrators/boundary.h) on scenes where they are the whole gradient: what moves is a
// constant emitter or a black occluder, so moving it changes the image only where its outline
// crosses the film (primary) or the sphere of directions seen from a surface point (secondary).
//  - Exact edge integrals: a uniformly emitting square's image sum under scale and depth (every
//    sample of the estimator carries the same value), and under sideways motion with a ramp adjoint.
//  - Finite differences in expectation (visibility makes same-seed differences of a few rays jump,
//    so both sides are averaged over seeds and compared with |z| < 4): an occluder in front and a
//    background behind, a rotating cube (split vertices, welded edges), a flat-shaded sphere mesh,
//    a strip crossing the near plane, a moving camera, and shadows moved by an occluder or a light
//    out of the camera's view (secondary term, depth 2 and 4). Negative controls in each: a zero
//    and a negated term fail the same comparison (a doubled one for the cube).
//  - Analytic secondary term: an occluder's edge across a square light above a point (closed form).
//  - Refusals: a null surface for the secondary term, an adjoint image of the wrong size.
//  - Cancellation: both terms compute nothing when their pass is cancelled.
#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include <atomic>
#include <cmath>
#include <string>
#include <vector>

#include "engine/core/errors.h"
#include "engine/integrators/boundary.h"
#include "engine/integrators/interior.h"
#include "engine/integrators/render.h"
#include "engine/io/image_io.h"
#include "engine/scene/scene_load.h"
#include "test_scenes.h"

using namespace bl;

namespace {

constexpr int kRes = 64;

nlohmann::json base_scene(int max_depth) {
  return {{"integrator", {{"spp", 16}, {"max_depth", max_depth}, {"rr_depth", 0}}},
          {"cameras",
           {{{"name", "main"},
             {"origin", {0, 0, 0}},
             {"target", {0, 0, -1}},
             {"up", {0, 1, 0}},
             {"fov", 40},
             {"resolution", {kRes, kRes}}}}},
          {"materials", {{"black", {{"type", "diffuse"}, {"albedo", {0, 0, 0}}}}}},
          {"shapes", nlohmann::json::array()}};
}

nlohmann::json emitter_shape(const std::string& name, const std::string& type, const nlohmann::json& transform,
                             const nlohmann::json& radiance) {
  nlohmann::json s = {{"name", name}, {"type", type}, {"material", "black"}, {"transform", transform}};
  if (!radiance.is_null()) s["emitter"] = {{"radiance", radiance}};
  return s;
}

// An emitting square at depth 3, partly hidden (its right side) by a black square at depth 2, in
// front of a constant background.
nlohmann::json occluded_light_scene(int max_depth) {
  nlohmann::json j = base_scene(max_depth);
  j["environment"] = {{"type", "constant"}, {"radiance", {0.25, 0.25, 0.25}}};
  j["shapes"].push_back(
      emitter_shape("light", "rectangle", {{"scale", 0.5}, {"translate", {0, 0, -3}}}, {1.0, 0.5, 0.25}));
  j["shapes"].push_back(
      emitter_shape("blocker", "rectangle", {{"scale", 0.25}, {"translate", {0.25, 0.1, -2}}}, nullptr));
  return j;
}

std::unique_ptr<Scene> build(const nlohmann::json& j) {
  return build_json_scene(j, test::temp_dir("boundary") + "/scene.json");
}

int mesh_index(const Scene& scene, const std::string& name) {
  for (size_t i = 0; i < scene.meshes.size(); ++i)
    if (scene.meshes[i].name == name) return int(i);
  FAIL("no mesh " << name);
  return -1;
}

Vec3f centre(const Mesh& m) {
  Vec3d c(0.0);
  for (size_t v = 0; v < m.vertex_count(); ++v) c += Vec3d(m.positions[v]);
  return Vec3f(c / double(m.vertex_count()));
}

Image constant_adjoint(float value) {
  Image a(kRes, kRes, 3);
  for (float& v : a.data) v = value;
  return a;
}

double functional(const Image& image, const Image& adjoint) {
  double f = 0;
  for (size_t i = 0; i < image.data.size(); ++i) f += double(image.data[i]) * double(adjoint.data[i]);
  return f;
}

// A pose direction: translate, rotate (axis-angle) and scale about `pivot`, applied to one mesh.
struct PoseDirection {
  Vec3d translate{0.0}, rotate{0.0}, scale{0.0};
  double along(const PoseGradient& g) const {
    return dot(translate, g.translate) + dot(rotate, g.rotate) + dot(scale, g.scale);
  }
};

// Moves mesh `mi` from its `rest` state by h along `dir` (exact rotation about the axis for
// rotations; vertex normals turn with it and follow the inverse transpose of the scale) and
// re-prepares.
void apply_pose(Scene& scene, int mi, const Mesh& rest, const Vec3f& pivot, const PoseDirection& dir, double h) {
  Mesh& m = scene.meshes[size_t(mi)];
  const double angle = length(dir.rotate) * h;
  const Vec3d axis = length(dir.rotate) > 0 ? dir.rotate / length(dir.rotate) : Vec3d(0, 0, 1);
  auto rotate = [&](const Vec3d& r) {  // Rodrigues
    return r * std::cos(angle) + cross(axis, r) * std::sin(angle) + axis * (dot(axis, r) * (1 - std::cos(angle)));
  };
  const Vec3d scale = Vec3d(1.0) + dir.scale * h;
  for (size_t v = 0; v < m.vertex_count(); ++v) {
    const Vec3d r = Vec3d(rest.positions[v] - pivot) * scale;
    m.positions[v] = Vec3f(Vec3d(pivot) + rotate(r) + dir.translate * h);
    if (!m.normals.empty()) m.normals[v] = Vec3f(rotate(normalize(Vec3d(rest.normals[v]) / scale)));
  }
  scene.prepare();
}

struct Estimate {
  double mean = 0, stderr_ = 0;
};

Estimate summarize(const std::vector<double>& xs) {
  double m = 0;
  for (double x : xs) m += x;
  m /= double(xs.size());
  double v = 0;
  for (double x : xs) v += (x - m) * (x - m);
  v /= double(xs.size() - 1);
  return {m, std::sqrt(v / double(xs.size()))};
}

// Boundary-term directional derivative of F along `dir` over `seeds` seeds.
Estimate boundary_derivative(const Scene& scene, int mi, const Vec3f& pivot, const Image& adjoint,
                             const PoseDirection& dir, int seeds, uint64_t samples) {
  std::vector<double> xs;
  for (int s = 0; s < seeds; ++s) {
    BoundaryOptions o;
    o.samples = samples;
    o.seed = uint64_t(1000 + s);
    o.meshes = {mi};
    const GeometryGradient g = primary_boundary_gradient(scene, adjoint, o);
    xs.push_back(dir.along(pose_gradient(scene.meshes[size_t(mi)], g.vertices[0], pivot)));
  }
  return summarize(xs);
}

// Central differences of F = ⟨adjoint, render⟩ at step ±h, the same seed on both sides, over seeds.
Estimate finite_difference(Scene& scene, int mi, const Vec3f& pivot, const Image& adjoint, const PoseDirection& dir,
                           double h, int seeds, int spp) {
  const Mesh rest = scene.meshes[size_t(mi)];
  std::vector<double> xs;
  for (int s = 0; s < seeds; ++s) {
    PassOptions o;
    o.spp = spp;
    o.seed = uint64_t(77 + s);
    o.progress = false;
    apply_pose(scene, mi, rest, pivot, dir, h);
    const double up = functional(render(scene, o), adjoint);
    apply_pose(scene, mi, rest, pivot, dir, -h);
    const double down = functional(render(scene, o), adjoint);
    xs.push_back((up - down) / (2 * h));
  }
  apply_pose(scene, mi, rest, pivot, dir, 0.0);
  return summarize(xs);
}

double z_score(const Estimate& a, const Estimate& b) {
  return (a.mean - b.mean) / std::sqrt(a.stderr_ * a.stderr_ + b.stderr_ * b.stderr_);
}

// The boundary term along a pose direction of mesh `mi` against central differences at step h
// (8 seeds each, 16 spp renders, 8192 edge samples): |z| < 4; negative controls: without the
// boundary term, or with its sign flipped, the same comparison fails. Returns the boundary estimate.
Estimate check_pose_derivative(Scene& scene, int mi, const PoseDirection& dir, double h, const std::string& what) {
  const Vec3f pivot = centre(scene.meshes[size_t(mi)]);
  const Image ones = constant_adjoint(1.f);
  const Estimate fd = finite_difference(scene, mi, pivot, ones, dir, h, 8, 16);
  const Estimate be = boundary_derivative(scene, mi, pivot, ones, dir, 8, 8192);
  const double z = z_score(be, fd);
  INFO(what << ": boundary " << be.mean << " ± " << be.stderr_ << ", finite differences " << fd.mean << " ± "
            << fd.stderr_ << ", z " << z);
  CHECK(std::abs(z) < 4);
  CHECK(std::abs(z_score(Estimate{0.0, 0.0}, fd)) > 4);
  CHECK(std::abs(z_score(Estimate{-be.mean, be.stderr_}, fd)) > 4);
  return be;
}

}  // namespace

TEST_CASE("a uniformly emitting square: the boundary term is the exact edge integral", "[boundary]") {
  nlohmann::json j = base_scene(1);
  j["shapes"].push_back(emitter_shape("square", "rectangle", {{"scale", 0.5}, {"translate", {0, 0, -3}}}, {1, 1, 1}));
  auto scene = build(j);
  const int mi = mesh_index(*scene, "square");
  const Camera& cam = scene->cameras[0];
  // Side 1 at distance 3: side in pixels, image sum F = 3 channels · area.
  const double px_per_unit = double(cam.width) / (2.0 * 3.0 * double(cam.tan_x));
  const double side = px_per_unit;
  const double area = side * side;
  const Vec3f pivot(0.f, 0.f, -3.f);

  // The render agrees with the analytic area (the pixel integral of a box filter).
  PassOptions po;
  po.spp = 64;
  po.progress = false;
  const Image ones = constant_adjoint(1.f);
  CHECK(functional(render(*scene, po), ones) == Approx(3.0 * area).epsilon(2e-3));

  BoundaryOptions o;
  o.samples = 4096;
  o.meshes = {mi};
  const GeometryGradient g = primary_boundary_gradient(*scene, ones, o);
  CHECK(g.edges == 4);  // the diagonal is neither a silhouette nor a crease
  CHECK(g.edge_length == Approx(4.0 * side).epsilon(1e-5));
  const PoseGradient pose = pose_gradient(scene->meshes[size_t(mi)], g.vertices[0], pivot);
  // Area ∝ s_x s_y and ∝ 1/(3 − t_z)²: for a uniform scale and for depth, every sample of the
  // estimator carries the same value, so these are exact.
  CHECK(pose.scale.x + pose.scale.y == Approx(6.0 * area).epsilon(1e-4));
  CHECK(std::abs(pose.scale.z) < 1e-6 * area);
  CHECK(pose.translate.z == Approx(2.0 * area).epsilon(1e-4));  // 3 · 2 · area / 3
  // One axis of scale, and rotation about the view axis (the area does not change), are exact
  // in expectation only (which edge a sample picks decides its value).
  PoseDirection sx, rz;
  sx.scale = Vec3d(1, 0, 0);
  rz.rotate = Vec3d(0, 0, 1);
  const Estimate scale_x = boundary_derivative(*scene, mi, pivot, ones, sx, 8, 65536);
  const Estimate rotate_z = boundary_derivative(*scene, mi, pivot, ones, rz, 8, 65536);
  INFO("dF/ds_x " << scale_x.mean << " ± " << scale_x.stderr_ << ", dF/dr_z " << rotate_z.mean << " ± "
                  << rotate_z.stderr_ << ", exact " << 3.0 * area << " and 0");
  CHECK(std::abs(scale_x.mean - 3.0 * area) < 4 * scale_x.stderr_);
  CHECK(scale_x.stderr_ < 0.01 * area);
  CHECK(std::abs(rotate_z.mean) < 4 * rotate_z.stderr_);
  CHECK(rotate_z.stderr_ < 0.01 * area);

  // A ramp adjoint a = floor(x) + 1/2: sliding sideways at px_per_unit pixels per unit changes F
  // by 3 · px_per_unit · side · (a(right edge) − a(left edge)).
  Image ramp(kRes, kRes, 3);
  for (int y = 0; y < kRes; ++y)
    for (int x = 0; x < kRes; ++x)
      for (int c = 0; c < 3; ++c) ramp.at(x, y, c) = float(x) + 0.5f;
  const double left = 0.5 * kRes - 0.5 * side, right = 0.5 * kRes + 0.5 * side;
  const double expected = 3.0 * px_per_unit * side * (std::floor(right) - std::floor(left));
  PoseDirection dir;
  dir.translate = Vec3d(1, 0, 0);
  const Estimate est = boundary_derivative(*scene, mi, pivot, ramp, dir, 8, 65536);
  INFO("dF/dtx " << est.mean << " ± " << est.stderr_ << ", exact " << expected);
  CHECK(std::abs(est.mean - expected) < 4 * est.stderr_ + 1e-4 * std::abs(expected));
  CHECK(est.stderr_ < 0.01 * std::abs(expected));
}

TEST_CASE("boundary term against finite differences in expectation, with occlusion and a background", "[boundary]") {
  nlohmann::json j = occluded_light_scene(3);
  auto scene = build(j);
  // Steps moving edges by 1–3 pixels; F is piecewise linear in these motions (kinks where a
  // corner crosses an edge), so central differences inside one piece have no truncation error.
  struct Case {
    const char* mesh;
    PoseDirection dir;
    double h;
  };
  std::vector<Case> cases;
  {
    // Steps small enough that no corner crosses another edge (F is then linear along them).
    PoseDirection d;
    d.translate = Vec3d(1, -0.3, 0);
    cases.push_back({"light", d, 0.05});
    PoseDirection s;
    s.scale = Vec3d(0.5, 1, 0);
    cases.push_back({"light", s, 0.04});
    PoseDirection e;
    e.translate = Vec3d(-1, 0.3, 0);
    cases.push_back({"blocker", e, 0.03});
    PoseDirection t;
    t.scale = Vec3d(1, -0.5, 0);
    cases.push_back({"blocker", t, 0.05});
  }
  for (const Case& c : cases) check_pose_derivative(*scene, mesh_index(*scene, c.mesh), c.dir, c.h, c.mesh);
}

TEST_CASE("a rotating emissive cube: welded edges, silhouettes from split vertices", "[boundary]") {
  nlohmann::json j = base_scene(2);
  j["shapes"].push_back(emitter_shape(
      "cube", "cube", {{"scale", 0.4}, {"rotate", {{"axis", {1, 1, 0}}, {"angle", 30}}}, {"translate", {0.1, 0, -3}}},
      {1, 1, 1}));
  auto scene = build(j);
  const int mi = mesh_index(*scene, "cube");
  REQUIRE(scene->meshes[size_t(mi)].vertex_count() == 24);  // split per face
  const Vec3f pivot = centre(scene->meshes[size_t(mi)]);
  const Image ones = constant_adjoint(1.f);
  BoundaryOptions o;
  o.samples = 1024;
  o.meshes = {mi};
  // Twelve welded edges; the faces' shared edges are creases (flat normals), all candidates.
  CHECK(primary_boundary_gradient(*scene, ones, o).edges == 12);
  PoseDirection r;
  r.rotate = Vec3d(0, 1, 0.2);
  const Estimate be = check_pose_derivative(*scene, mi, r, 0.05, "cube");
  // Counting each split copy of an edge as a boundary of its own would double the silhouettes.
  const Estimate fd = finite_difference(*scene, mi, pivot, ones, r, 0.05, 8, 16);
  CHECK(std::abs(z_score(Estimate{2 * be.mean, 2 * be.stderr_}, fd)) > 4);
}

TEST_CASE("a moving camera: the boundary term of its pose against finite differences", "[boundary]") {
  nlohmann::json j = occluded_light_scene(2);
  // Across the film's left border (the film spans ±1.09 at depth 3): turning the camera changes
  // how much of it is seen.
  j["shapes"].push_back(
      emitter_shape("side", "rectangle", {{"scale", 0.3}, {"translate", {-1.2, 0, -3}}}, {0.5, 1.0, 1.0}));
  auto scene = build(j);
  const Image ones = constant_adjoint(1.f);
  const Camera rest = scene->cameras[0];
  // Moves the camera rigidly by h along (translate, rotate) and renders F.
  auto moved = [&](const Vec3d& translate, const Vec3d& rotate, double h, uint64_t seed) {
    Camera& cam = scene->cameras[0];
    cam = rest;
    const double angle = length(rotate) * h;
    const Vec3d axis = length(rotate) > 0 ? rotate / length(rotate) : Vec3d(0, 0, 1);
    auto rot = [&](const Vec3d& v) {
      return v * std::cos(angle) + cross(axis, v) * std::sin(angle) + axis * (dot(axis, v) * (1 - std::cos(angle)));
    };
    cam.origin = Vec3f(Vec3d(rest.origin) + translate * h);
    cam.target = Vec3f(Vec3d(cam.origin) + rot(Vec3d(rest.target - rest.origin)));
    cam.up = Vec3f(rot(Vec3d(rest.up)));
    cam.update();
    PassOptions o;
    o.spp = 16;
    o.seed = seed;
    o.progress = false;
    return functional(render(*scene, o), ones);
  };
  struct Case {
    Vec3d translate, rotate;
    double h;
  };
  // Steps of 1–2 pixels at the light's depth, no corner crossing an edge.
  for (const Case& c : {Case{Vec3d(-1, 0.3, 0), Vec3d(0.0), 0.03}, Case{Vec3d(0, 0, 1), Vec3d(0.0), 0.1},
                        Case{Vec3d(0.0), Vec3d(0.2, -1, 0), 0.01}}) {
    std::vector<double> fd, be;
    for (int s = 0; s < 8; ++s) {
      const double up = moved(c.translate, c.rotate, c.h, uint64_t(5 + s));
      const double down = moved(c.translate, c.rotate, -c.h, uint64_t(5 + s));
      fd.push_back((up - down) / (2 * c.h));
    }
    scene->cameras[0] = rest;
    for (int s = 0; s < 8; ++s) {
      BoundaryOptions o;
      o.samples = 8192;
      o.seed = uint64_t(300 + s);
      const CameraPoseGradient g =
          camera_pose_gradient(*scene, primary_boundary_gradient(*scene, ones, o), scene->cameras[0]);
      be.push_back(dot(c.translate, g.origin) + dot(c.rotate, g.rotate));
    }
    const Estimate f = summarize(fd), b = summarize(be);
    const double z = z_score(b, f);
    INFO("camera " << c.translate.x << "," << c.translate.y << "," << c.translate.z << " / " << c.rotate.x << ","
                   << c.rotate.y << "," << c.rotate.z << ": boundary " << b.mean << " ± " << b.stderr_
                   << ", finite differences " << f.mean << " ± " << f.stderr_ << ", z " << z);
    CHECK(std::abs(z) < 4);
    CHECK(std::abs(z_score(Estimate{0.0, 0.0}, f)) > 4);
    CHECK(std::abs(z_score(Estimate{-b.mean, b.stderr_}, f)) > 4);
  }
}

TEST_CASE("edges crossing the near plane are clipped, not dropped", "[boundary]") {
  // A long emitting strip on the ground, x in [−0.2, 3], runs from behind the camera to z = −4:
  // its left side enters the film through its border from behind the camera (the right side is
  // never seen). Sliding it sideways moves only that side (the far edge slides along itself).
  nlohmann::json j = base_scene(1);
  j["cameras"][0]["origin"] = {0, 1, 0};
  j["cameras"][0]["target"] = {0, 0.5, -1};
  j["environment"] = {{"type", "constant"}, {"radiance", {0.25, 0.25, 0.25}}};
  j["shapes"].push_back(emitter_shape(
      "strip", "rectangle",
      {{"scale", {1.6, 3, 1}}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", -90}}}, {"translate", {1.4, 0, -1}}},
      {1.0, 0.8, 0.6}));
  auto scene = build(j);
  const int mi = mesh_index(*scene, "strip");
  PoseDirection tx, ry, tz;
  tx.translate = Vec3d(1, 0, 0);
  ry.rotate = Vec3d(0, 1, 0);
  tz.translate = Vec3d(0, 0, 1);
  for (const auto& [dir, h] : {std::pair{tx, 0.03}, std::pair{ry, 0.01}, std::pair{tz, 0.05}})
    check_pose_derivative(*scene, mi, dir, h, "strip");
}

TEST_CASE("an emitting sphere mesh: its silhouette loop among 2208 faces", "[boundary]") {
  // Flat shading: with interpolated normals, the side a one-sided emitter emits on is decided by
  // the shading normal, which turns away from the camera in a band inside the silhouette; the
  // band's inner border is a discontinuity that is no mesh edge, which edge sampling cannot see
  // (boundary.h). Measured with smooth normals, the scale direction below: boundary term 500 ± 11
  // against finite differences 2505 ± 8.
  nlohmann::json j = base_scene(2);
  j["environment"] = {{"type", "constant"}, {"radiance", {0.25, 0.25, 0.25}}};
  j["shapes"].push_back({{"name", "ball"},
                         {"type", "sphere"},
                         {"segments", 48},
                         {"face_normals", true},
                         {"material", "black"},
                         {"emitter", {{"radiance", {1.0, 0.8, 0.6}}}},
                         {"transform", {{"scale", 0.6}, {"translate", {0.2, -0.1, -3}}}}});
  auto scene = build(j);
  const int mi = mesh_index(*scene, "ball");
  PoseDirection s, t;
  s.scale = Vec3d(1, 0.5, 0.2);
  t.translate = Vec3d(0.3, -1, 1);
  check_pose_derivative(*scene, mi, s, 0.03, "sphere scale");
  check_pose_derivative(*scene, mi, t, 0.05, "sphere translate");
}

TEST_CASE("folds of a flat-shaded mesh along its outline add no jump of their own", "[boundary]") {
  // A black, flat-shaded sphere of small faces (~0.5 pixel) against a white sky: many of its folds
  // run nearly along the outline, where one of a fold's side rays (10^-3 pixel off the edge) can
  // miss the mesh and see the sky. Counting that jump added the outline's contrast a second time
  // (an audit: +30% at 32², the bundled deform sphere); a fold's sample now counts only where both
  // sides meet its faces.
  nlohmann::json j = base_scene(1);
  j["environment"] = {{"type", "constant"}, {"radiance", {1, 1, 1}}};
  j["shapes"].push_back({{"name", "ball"},
                         {"type", "sphere"},
                         {"segments", 96},
                         {"face_normals", true},
                         {"material", "black"},
                         {"transform", {{"scale", 0.15}, {"translate", {0.1, -0.05, -3}}}}});
  auto scene = build(j);
  const int mi = mesh_index(*scene, "ball");
  const Vec3f pivot = centre(scene->meshes[size_t(mi)]);
  const Image ones = constant_adjoint(1.f);
  PoseDirection s, t;
  s.scale = Vec3d(1, 1, 1);
  t.translate = Vec3d(0.2, 0, 1);  // towards the camera: the outline grows
  for (const PoseDirection& dir : {s, t}) {
    const Estimate fd = finite_difference(*scene, mi, pivot, ones, dir, 0.02, 64, 16);
    const Estimate be = boundary_derivative(*scene, mi, pivot, ones, dir, 16, 1 << 16);
    const double z = z_score(be, fd);
    INFO("scale " << dir.scale.x << ", translate z " << dir.translate.z << ": boundary " << be.mean << " ± "
                  << be.stderr_ << ", finite differences " << fd.mean << " ± " << fd.stderr_ << ", z " << z);
    CHECK(std::abs(z) < 4);
    // The comparison resolves a 10% error in the scale direction (the folds' jump was +7.8% there:
    // boundary −392 ± 3 against finite differences −364 ± 5, z −4.8; the translation, which moves
    // fewer folds along the outline, was within its noise).
    if (dir.scale.x != 0) CHECK(std::abs(z_score(Estimate{be.mean * 1.1, be.stderr_}, fd)) > 4);
  }
}

namespace {

// A diffuse floor and back wall lit by a small light above them, a black square between light
// and floor casting a shadow; the camera looks at the floor and sees neither the light nor the
// square.
nlohmann::json shadow_scene(int max_depth) {
  nlohmann::json j = base_scene(max_depth);
  j["cameras"][0]["origin"] = {0, 0.6, 3};
  j["cameras"][0]["target"] = {0, 0, 0};
  j["materials"]["white"] = {{"type", "diffuse"}, {"albedo", {0.8, 0.8, 0.8}}};
  j["shapes"].push_back({{"name", "floor"},
                         {"type", "rectangle"},
                         {"material", "white"},
                         {"transform", {{"scale", 2}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", -90}}}}}});
  // A wall behind: light reaches the floor after a bounce too (when the depth allows), through
  // the same shadowing.
  j["shapes"].push_back({{"name", "wall"},
                         {"type", "rectangle"},
                         {"material", "white"},
                         {"transform", {{"scale", 2}, {"translate", {0, 1, -1.5}}}}});
  j["shapes"].push_back(emitter_shape(
      "light", "rectangle",
      {{"scale", 0.3}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", 90}}}, {"translate", {0, 2, 0}}}, {10, 10, 10}));
  j["shapes"].push_back(emitter_shape(
      "blocker", "rectangle",
      {{"scale", 0.25}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", -90}}}, {"translate", {0.1, 1.2, 0.05}}}, nullptr));
  return j;
}

// The whole derivative (primary boundary + interior + secondary boundary) along a pose direction
// of mesh `mi` over seeds, and the same without the interior term (a negative control).
struct GeometryEstimate {
  Estimate total, without_interior;
  double primary = 0, interior = 0, secondary = 0;  // means of the terms
};
GeometryEstimate geometry_derivative(const Scene& scene, int mi, const Vec3f& pivot, const Image& adjoint,
                                     const PoseDirection& dir, int seeds) {
  std::vector<double> total, without;
  GeometryEstimate r;
  const Mesh& m = scene.meshes[size_t(mi)];
  for (int s = 0; s < seeds; ++s) {
    BoundaryOptions o;
    o.samples = 8192;
    o.seed = uint64_t(300 + s);
    o.meshes = {mi};
    PathGeometryOptions po;
    po.spp = 4;
    po.seed = uint64_t(700 + s);
    po.meshes = {mi};
    po.edge_samples = 8;
    po.boundary = false;
    const GeometryGradient gi = path_geometry_gradient(scene, adjoint, po);
    po.boundary = true;
    po.interior = false;
    const GeometryGradient gs = path_geometry_gradient(scene, adjoint, po);
    const double primary = dir.along(pose_gradient(m, primary_boundary_gradient(scene, adjoint, o).vertices[0], pivot));
    const double interior = dir.along(pose_gradient(m, gi.vertices[0], gi.normals[0], pivot));
    const double secondary = dir.along(pose_gradient(m, gs.vertices[0], gs.normals[0], pivot));
    total.push_back(primary + interior + secondary);
    without.push_back(primary + secondary);
    r.primary += primary / seeds;
    r.interior += interior / seeds;
    r.secondary += secondary / seeds;
  }
  r.total = summarize(total);
  r.without_interior = summarize(without);
  return r;
}

}  // namespace

// [expectation]: not under the sanitizers; the taped-oracle case runs the same secondary term.
TEST_CASE("secondary visibility: a moving occluder and a moving light move a shadow", "[boundary][expectation]") {
  for (int depth : {2, 4}) {
    auto scene = build(shadow_scene(depth));
    const Image ones = constant_adjoint(1.f);
    struct Case {
      const char* mesh;
      PoseDirection dir;
      double h;
    };
    PoseDirection bx, bs, ls, lx;
    bx.translate = Vec3d(0.3, 1, 0);
    bs.scale = Vec3d(1, 0, 1);
    ls.scale = Vec3d(1, 0, 1);
    lx.translate = Vec3d(1, 0, 0);
    for (const Case& c :
         {Case{"blocker", bx, 0.03}, Case{"blocker", bs, 0.05}, Case{"light", lx, 0.05}, Case{"light", ls, 0.1}}) {
      const int mi = mesh_index(*scene, c.mesh);
      const Vec3f pivot = centre(scene->meshes[size_t(mi)]);
      const Estimate fd = finite_difference(*scene, mi, pivot, ones, c.dir, c.h, 8, 16);
      const GeometryEstimate ge = geometry_derivative(*scene, mi, pivot, ones, c.dir, 8);
      const double z = z_score(ge.total, fd);
      INFO("depth " << depth << ", " << c.mesh << " t " << c.dir.translate.x << "," << c.dir.translate.y << ","
                    << c.dir.translate.z << " s " << c.dir.scale.x << "," << c.dir.scale.y << "," << c.dir.scale.z
                    << ": total " << ge.total.mean << " ± " << ge.total.stderr_ << " (primary " << ge.primary
                    << ", interior " << ge.interior << ", secondary " << ge.secondary << "), finite differences "
                    << fd.mean << " ± " << fd.stderr_ << ", z " << z);
      CHECK(std::abs(z) < 4);
      CHECK(ge.primary == 0.0);  // the camera sees neither shape
      CHECK(std::abs(z_score(Estimate{0.0, 0.0}, fd)) > 4);
      CHECK(std::abs(z_score(Estimate{-ge.total.mean, ge.total.stderr_}, fd)) > 4);
      // A growing light sends more light: that is interior (its samples' area), not visibility.
      if (c.dir.scale.x != 0 && std::string(c.mesh) == "light") CHECK(std::abs(z_score(ge.without_interior, fd)) > 4);
    }
  }
}

TEST_CASE("secondary visibility, analytic: an occluder's edge across a square light above a point", "[boundary]") {
  // A point x = 0 on a diffuse floor (albedo ρ), a square light of side 2a and radiance 1 at
  // height H above it facing down, a black occluder at height h whose edge x = c covers the
  // light's part x_l > c·H/h (its other edges project outside the light). A camera with a tiny
  // film looks at x from the side, under the occluder: its pixel is ρ/π · E(x), and sliding the
  // occluder by δ along x moves its shadow line on the light plane by δ·H/h, so
  //   dE/dc = (H/h) ∫_{−a}^{a} H² / (x_l² + H² + z²)² dz at x_l = c·H/h
  //        = (H/h) H² [a / (A² (A² + a²)) + atan(a/A) / A³],  A² = x_l² + H².
  const double rho = 0.5, a = 0.5, H = 2, h = 1, c = 0.1;
  nlohmann::json j = base_scene(2);
  j["cameras"][0] = {{"name", "point"}, {"origin", {3, 0.3, 0}}, {"target", {0, 0, 0}},
                     {"up", {0, 1, 0}}, {"fov", 0.05},           {"resolution", {1, 1}}};
  j["materials"]["grey"] = {{"type", "diffuse"}, {"albedo", {rho, rho, rho}}};
  j["shapes"].push_back({{"name", "floor"},
                         {"type", "rectangle"},
                         {"material", "grey"},
                         {"transform", {{"scale", 4}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", -90}}}}}});
  j["shapes"].push_back(emitter_shape(
      "light", "rectangle", {{"scale", a}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", 90}}}, {"translate", {0, H, 0}}},
      {1, 1, 1}));
  j["shapes"].push_back(emitter_shape(
      "blocker", "rectangle",
      {{"scale", {1, 2, 1}}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", -90}}}, {"translate", {c + 1, h, 0}}},
      nullptr));
  auto scene = build(j);
  Image ones(1, 1, 3);
  for (float& v : ones.data) v = 1.f;

  // The setup: the render matches ρ/π · E(x), E by quadrature over the visible part of the light.
  const double xl = c * H / h;
  double e = 0;
  const int n = 400;
  for (int ix = 0; ix < n; ++ix)
    for (int iz = 0; iz < n; ++iz) {
      const double x = -a + (xl + a) * (ix + 0.5) / n, z = -a + 2 * a * (iz + 0.5) / n;
      const double r2 = x * x + z * z + H * H;
      e += H * H / (r2 * r2) * ((xl + a) / n) * (2 * a / n);
    }
  PassOptions po;
  po.spp = 1 << 16;
  po.progress = false;
  CHECK(functional(render(*scene, po), ones) == Approx(3 * rho / kPi * e).epsilon(0.01));

  const double A2 = xl * xl + H * H, A = std::sqrt(A2);
  const double exact = 3 * rho / kPi * (H / h) * H * H * (a / (A2 * (A2 + a * a)) + std::atan(a / A) / (A2 * A));
  const int mi = mesh_index(*scene, "blocker");
  std::vector<double> xs;
  for (int s = 0; s < 8; ++s) {
    PathGeometryOptions so;
    so.spp = 1 << 15;
    so.seed = uint64_t(40 + s);
    so.meshes = {mi};
    xs.push_back(
        pose_gradient(scene->meshes[size_t(mi)], path_geometry_gradient(*scene, ones, so).vertices[0], Vec3f(0.f))
            .translate.x);
  }
  const Estimate est = summarize(xs);
  INFO("dF/dc " << est.mean << " ± " << est.stderr_ << ", exact " << exact);
  CHECK(std::abs(est.mean - exact) < 4 * est.stderr_);
  CHECK(est.stderr_ < 0.02 * exact);
  // The comparison has the power to see a factor of two (e.g. a missing H/h) or a lost sign.
  CHECK(std::abs(0.5 * est.mean - exact) > 4 * est.stderr_);
  CHECK(std::abs(-est.mean - exact) > 4 * est.stderr_);
}

TEST_CASE("the boundary terms refuse what they do not handle, in one line", "[boundary]") {
  nlohmann::json j = shadow_scene(2);
  j["materials"]["boundary"] = {{"type", "null"}};
  j["shapes"].push_back({{"name", "glass"},
                         {"type", "rectangle"},
                         {"material", "boundary"},
                         {"transform", {{"scale", 0.2}, {"translate", {0, 0.5, 0}}}}});
  auto scene = build(j);
  PathGeometryOptions so;
  so.spp = 1;
  try {
    path_geometry_gradient(*scene, constant_adjoint(1.f), so);
    FAIL("a scene with a null surface accepted by the path terms");
  } catch (const InputError& e) {
    CHECK(std::string(e.what()).find("null surfaces") != std::string::npos);
    CHECK(std::string(e.what()).find('\n') == std::string::npos);
  }
  // An adjoint image of the wrong size is an error naming both sizes, for either term.
  const Image small(8, 8, 3);
  CHECK_THROWS_WITH(primary_boundary_gradient(*scene, small, BoundaryOptions{}),
                    Catch::Contains("8x8x3") && Catch::Contains("64x64x3"));
  CHECK_THROWS_AS(path_geometry_gradient(*scene, small, so), InputError);
}

TEST_CASE("the geometry passes stop when their pass is cancelled", "[boundary]") {
  // Python's Ctrl-C (and its exit) set PassOptions::cancel; the geometry passes ran to their end
  // regardless. A pass cancelled before it starts now computes nothing: its sums stay zero, where
  // the same pass not cancelled gives a gradient (no wall-clock assertion: with the flag ignored
  // the zero checks fail).
  auto any_nonzero = [](const GeometryGradient& g) {
    for (const auto& vertices : g.vertices)
      for (const Vec3d& v : vertices)
        if (v.x != 0 || v.y != 0 || v.z != 0) return true;
    return false;
  };
  std::atomic<bool> cancel{false};
  auto shadow = build(shadow_scene(2));  // the blocker's shadow: the path terms
  PathGeometryOptions so;
  so.spp = 2;
  so.meshes = {mesh_index(*shadow, "blocker")};
  so.cancel = &cancel;
  CHECK(any_nonzero(path_geometry_gradient(*shadow, constant_adjoint(1.f), so)));
  nlohmann::json j = base_scene(1);  // an emitting square in view: the primary term
  j["shapes"].push_back(emitter_shape("square", "rectangle", {{"scale", 0.5}, {"translate", {0, 0, -3}}}, {1, 1, 1}));
  auto square = build(j);
  BoundaryOptions bo;
  bo.samples = 4096;
  bo.cancel = &cancel;
  CHECK(any_nonzero(primary_boundary_gradient(*square, constant_adjoint(1.f), bo)));
  cancel = true;
  CHECK_FALSE(any_nonzero(path_geometry_gradient(*shadow, constant_adjoint(1.f), so)));
  CHECK_FALSE(any_nonzero(primary_boundary_gradient(*square, constant_adjoint(1.f), bo)));
}

namespace {

// A Cornell box open towards the camera: white floor, ceiling and back wall, red and green side
// walls, a light under the ceiling; a diffuse cube (flat shading, split vertices) and a
// flat-shaded sphere of 24 segments, both a little above the floor (a shape pushed into another
// makes their intersection a discontinuity that is no mesh edge). Everything scatters:
// interreflections, shadows, and the light seen directly.
nlohmann::json cornell_scene(int max_depth) {
  nlohmann::json j = base_scene(max_depth);
  j["cameras"][0]["origin"] = {0, 0, 3.4};
  j["cameras"][0]["target"] = {0, 0, 0};
  j["materials"]["white"] = {{"type", "diffuse"}, {"albedo", {0.7, 0.7, 0.7}}};
  j["materials"]["red"] = {{"type", "diffuse"}, {"albedo", {0.7, 0.1, 0.1}}};
  j["materials"]["green"] = {{"type", "diffuse"}, {"albedo", {0.1, 0.7, 0.1}}};
  auto wall = [&](const char* name, const char* material, const nlohmann::json& rotate, const nlohmann::json& at) {
    nlohmann::json t = {{"translate", at}};
    if (!rotate.is_null()) t["rotate"] = rotate;
    j["shapes"].push_back({{"name", name}, {"type", "rectangle"}, {"material", material}, {"transform", t}});
  };
  wall("floor", "white", {{"axis", {1, 0, 0}}, {"angle", -90}}, {0, -1, 0});
  wall("ceiling", "white", {{"axis", {1, 0, 0}}, {"angle", 90}}, {0, 1, 0});
  wall("back", "white", nullptr, {0, 0, -1});
  wall("left", "red", {{"axis", {0, 1, 0}}, {"angle", 90}}, {-1, 0, 0});
  wall("right", "green", {{"axis", {0, 1, 0}}, {"angle", -90}}, {1, 0, 0});
  j["shapes"].push_back(emitter_shape(
      "light", "rectangle",
      {{"scale", 0.5}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", 90}}}, {"translate", {0, 0.98, 0}}}, {3, 3, 3}));
  j["shapes"].push_back(
      {{"name", "cube"},
       {"type", "cube"},
       {"material", "white"},
       {"transform",
        {{"scale", 0.3}, {"rotate", {{"axis", {0, 1, 0}}, {"angle", 20}}}, {"translate", {-0.35, -0.55, -0.2}}}}});
  j["shapes"].push_back({{"name", "sphere"},
                         {"type", "sphere"},
                         {"segments", 24},
                         {"face_normals", true},
                         {"material", "white"},
                         {"transform", {{"scale", 0.3}, {"translate", {0.4, -0.5, 0.25}}}}});
  return j;
}

}  // namespace

// [expectation]: not under the sanitizers; the taped-oracle case runs the same Cornell paths.
TEST_CASE("interreflections: a Cornell box with a moving cube, sphere and light against finite differences",
          "[boundary][interior][expectation]") {
  auto scene = build(cornell_scene(3));
  const Image ones = constant_adjoint(1.f);
  struct Case {
    const char* mesh;
    PoseDirection dir;
    double h;
  };
  PoseDirection t, r, s, lt;
  t.translate = Vec3d(1, 0.3, 0.5);
  r.rotate = Vec3d(0, 1, 0.3);
  s.scale = Vec3d(1, 1, 1);
  lt.translate = Vec3d(0.6, 0, 0.4);
  for (const Case& c : {Case{"cube", t, 0.02}, Case{"cube", r, 0.05}, Case{"cube", s, 0.05}, Case{"sphere", s, 0.05},
                        Case{"light", lt, 0.06}}) {
    const int mi = mesh_index(*scene, c.mesh);
    const Vec3f pivot = centre(scene->meshes[size_t(mi)]);
    const Estimate fd = finite_difference(*scene, mi, pivot, ones, c.dir, c.h, 8, 16);
    const GeometryEstimate ge = geometry_derivative(*scene, mi, pivot, ones, c.dir, 8);
    const double z = z_score(ge.total, fd);
    INFO(c.mesh << " t " << c.dir.translate.x << "," << c.dir.translate.y << "," << c.dir.translate.z << " r "
                << c.dir.rotate.y << " s " << c.dir.scale.x << ": total " << ge.total.mean << " ± " << ge.total.stderr_
                << " (primary " << ge.primary << ", interior " << ge.interior << ", secondary " << ge.secondary
                << "), finite differences " << fd.mean << " ± " << fd.stderr_ << ", z " << z);
    CHECK(std::abs(z) < 4);
    CHECK(std::abs(z_score(Estimate{0.0, 0.0}, fd)) > 4);
    CHECK(std::abs(z_score(Estimate{-ge.total.mean, ge.total.stderr_}, fd)) > 4);
    // Where the interior term is large against the noise, leaving it out fails (checked by hand for
    // the other cases: |z| 0.2–2.5 without it, the interior being 7–25% of the total there).
    if (c.dir.rotate.y != 0 || std::string(c.mesh) == "light") CHECK(std::abs(z_score(ge.without_interior, fd)) > 4);
  }
}

namespace {

// A smooth-shaded dome (a 12×12 grid, z = −0.2 (x² + y²), analytic vertex normals) filling the
// film, lit by a tilted square light; nothing else. Its shading normals are interpolated, so its
// interior derivative runs through the vertex normals (they turn with a rotation).
nlohmann::json dome_scene() {
  nlohmann::json j = base_scene(3);
  j["cameras"][0]["origin"] = {0, 0, 3};
  j["cameras"][0]["target"] = {0, 0, 0};
  j["cameras"][0]["fov"] = 30;
  j["materials"]["white"] = {{"type", "diffuse"}, {"albedo", {0.7, 0.7, 0.7}}};
  j["shapes"].push_back(test::dome_shape("white"));
  j["shapes"].push_back(emitter_shape(
      "light", "rectangle",
      {{"scale", 0.4}, {"rotate", {{"axis", {1, 0, 0}}, {"angle", 50}}}, {"translate", {0.3, 1.6, 1.6}}}, {6, 6, 6}));
  return j;
}

}  // namespace

// [expectation]: not under the sanitizers; the taped-oracle case runs the same dome.
TEST_CASE("a smooth-shaded dome: interior derivatives through interpolated vertex normals",
          "[boundary][interior][expectation]") {
  auto scene = build(dome_scene());
  const int mi = mesh_index(*scene, "dome");
  REQUIRE_FALSE(scene->meshes[size_t(mi)].normals.empty());
  const Image ones = constant_adjoint(1.f);
  const Vec3f pivot = centre(scene->meshes[size_t(mi)]);
  PoseDirection r, s, t;
  r.rotate = Vec3d(1, 0.5, 0);
  s.scale = Vec3d(1, 1, 1);
  t.translate = Vec3d(0, 0.3, 1);
  for (const PoseDirection& dir : {r, s, t}) {
    const Estimate fd = finite_difference(*scene, mi, pivot, ones, dir, 0.01, 8, 16);
    const GeometryEstimate ge = geometry_derivative(*scene, mi, pivot, ones, dir, 8);
    // The same without the vertex normals' share (normals held still as the positions move).
    std::vector<double> xs;
    for (int k = 0; k < 8; ++k) {
      PathGeometryOptions po;
      po.spp = 4;
      po.seed = uint64_t(700 + k);
      po.meshes = {mi};
      po.boundary = false;
      const GeometryGradient g = path_geometry_gradient(*scene, ones, po);
      xs.push_back(dir.along(pose_gradient(scene->meshes[size_t(mi)], g.vertices[0], g.normals[0], pivot)) -
                   dir.along(pose_gradient(scene->meshes[size_t(mi)], g.vertices[0], pivot)));
    }
    const Estimate normal_share = summarize(xs);
    const double z = z_score(ge.total, fd);
    INFO("r " << dir.rotate.x << " s " << dir.scale.x << " t " << dir.translate.z << ": total " << ge.total.mean
              << " ± " << ge.total.stderr_ << " (primary " << ge.primary << ", interior " << ge.interior
              << " of which normals " << normal_share.mean << ", secondary " << ge.secondary << "), fd " << fd.mean
              << " ± " << fd.stderr_ << ", z " << z);
    CHECK(std::abs(z) < 4);
    CHECK(std::abs(z_score(Estimate{0.0, 0.0}, fd)) > 4);
    if (dir.rotate.x != 0) {
      // Rotating turns the normals: leaving their share out fails.
      CHECK(std::abs(z_score(Estimate{ge.total.mean - normal_share.mean, ge.total.stderr_}, fd)) > 4);
    }
  }
}

TEST_CASE("the edge hierarchy and the scan of every edge estimate the same secondary term", "[boundary]") {
  // A shadow cast by a flat-shaded sphere of 2208 faces (silhouette candidates depend on the
  // shading point) and the square blocker: the hierarchy skips subtrees whose faces all face x or
  // all face away, so a wrong cone test would lose silhouettes and bias the estimate.
  nlohmann::json j = shadow_scene(2);
  j["shapes"].push_back({{"name", "ball"},
                         {"type", "sphere"},
                         {"segments", 48},
                         {"face_normals", true},
                         {"material", "black"},
                         {"transform", {{"scale", 0.2}, {"translate", {-0.5, 0.8, 0.2}}}}});
  auto scene = build(j);
  const int mi = mesh_index(*scene, "ball");
  const Image ones = constant_adjoint(1.f);
  const Vec3f pivot = centre(scene->meshes[size_t(mi)]);
  PoseDirection tx, grow;
  tx.translate = Vec3d(1, 0, 0);
  grow.scale = Vec3d(1, 1, 1);
  for (const PoseDirection& dir : {tx, grow}) {
    std::vector<double> tree, scan;
    for (int s = 0; s < 8; ++s) {
      PathGeometryOptions po;
      po.spp = 4;
      po.seed = uint64_t(60 + s);
      po.meshes = {mi};
      po.interior = false;
      po.edge_samples = 8;
      tree.push_back(dir.along(
          pose_gradient(scene->meshes[size_t(mi)], path_geometry_gradient(*scene, ones, po).vertices[0], pivot)));
      po.edge_hierarchy = false;
      scan.push_back(dir.along(
          pose_gradient(scene->meshes[size_t(mi)], path_geometry_gradient(*scene, ones, po).vertices[0], pivot)));
    }
    const Estimate a = summarize(tree), b = summarize(scan);
    INFO("translate " << dir.translate.x << " scale " << dir.scale.x << ": hierarchy " << a.mean << " ± " << a.stderr_
                      << ", scan " << b.mean << " ± " << b.stderr_);
    CHECK(std::abs(z_score(a, b)) < 4);
    CHECK(std::abs(a.mean) > 4 * a.stderr_);  // a derivative the comparison can see
  }
}

// [expectation]: the whole derivative against finite differences over seeds.
TEST_CASE("discontinuities along edges between coplanar faces, and a face wound the other way",
          "[boundary][expectation]") {
  // Found by an audit (each case failed with |z| 9-37 before): the edge table dropped every edge
  // between coplanar faces, so a texture atlas's uv seam and split vertex normals on a flat card
  // were no discontinuity; and the silhouette test read face normals from the winding, so one
  // face wound the other way on a smooth mesh hid silhouettes.
  const std::string dir = test::temp_dir("boundary-seams");
  Image atlas(2, 1, 3);  // a red texel and a blue one, a uv seam between the card's two triangles
  atlas.data = {0.9f, 0.1f, 0.1f, 0.1f, 0.1f, 0.9f};
  write_image(dir + "/atlas.pfm", atlas);
  const nlohmann::json square = {{-0.5, -0.5, -2}, {0.5, -0.5, -2}, {0.5, 0.5, -2},
                                 {-0.5, -0.5, -2}, {0.5, 0.5, -2},  {-0.5, 0.5, -2}};
  struct Case {
    const char* what;
    nlohmann::json scene;
    Image adjoint;
    PoseDirection dir;
    double h;
  };
  std::vector<Case> cases;
  Image red_ramp(kRes, kRes, 3), ramp(kRes, kRes, 3);
  for (int y = 0; y < kRes; ++y)
    for (int x = 0; x < kRes; ++x) {
      red_ramp.at(x, y, 0) = float(x) / kRes;  // a ramp: a sideways move is not a symmetry
      for (int c = 0; c < 3; ++c) ramp.at(x, y, c) = float(x) / kRes;
    }
  PoseDirection sideways, tilted;
  sideways.translate = Vec3d(1, 0, 0);
  tilted.translate = Vec3d(1, 0.5, 0);
  {
    nlohmann::json j = base_scene(2);
    j["environment"] = {{"type", "constant"}, {"radiance", {0.5, 0.5, 0.5}}};
    j["materials"]["atlas"] = {{"type", "diffuse"},
                               {"albedo", {{"type", "bitmap"}, {"file", dir + "/atlas.pfm"}, {"wrap", "clamp"}}}};
    j["shapes"].push_back({{"name", "card"},
                           {"type", "mesh"},
                           {"material", "atlas"},
                           {"positions", square},
                           {"indices", {{0, 1, 2}, {3, 4, 5}}},
                           {"uvs", {{0.1, 0.5}, {0.1, 0.5}, {0.1, 0.5}, {0.9, 0.5}, {0.9, 0.5}, {0.9, 0.5}}}});
    cases.push_back({"uv seam", j, red_ramp, sideways, 0.004});
  }
  {
    nlohmann::json j = base_scene(2);
    j["materials"]["white"] = {{"type", "diffuse"}, {"albedo", {0.8, 0.8, 0.8}}};
    j["shapes"].push_back(
        {{"name", "card"},
         {"type", "mesh"},
         {"material", "white"},
         {"positions", square},
         {"indices", {{0, 1, 2}, {3, 4, 5}}},
         {"normals", {{0, 0, 1}, {0, 0, 1}, {0, 0, 1}, {0.6, 0, 0.8}, {0.6, 0, 0.8}, {0.6, 0, 0.8}}}});
    j["shapes"].push_back(emitter_shape(
        "light", "rectangle",
        {{"scale", 0.3}, {"rotate", {{"axis", {0, 1, 0}}, {"angle", -60}}}, {"translate", {1.5, 0, -1.5}}},
        {10, 10, 10}));
    cases.push_back({"split normals", j, constant_adjoint(1.f), tilted, 0.01});
  }
  {
    nlohmann::json j = base_scene(1);
    j["environment"] = {{"type", "constant"}, {"radiance", {1, 1, 1}}};
    j["shapes"].push_back(
        {{"name", "card"},
         {"type", "mesh"},
         {"material", "black"},
         {"positions", {{0.5, 0, 0}, {-0.5, 0, 0}, {0, 0.5, 0}, {0, -0.5, 0}, {0, 0, 0.5}, {0, 0, -0.5}}},
         {"normals", {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}}},
         // The first face wound the other way round from the others.
         {"indices", {{0, 4, 2}, {0, 5, 2}, {0, 4, 3}, {0, 3, 5}, {1, 4, 2}, {1, 2, 5}, {1, 3, 4}, {1, 5, 3}}},
         {"transform", {{"translate", {0, 0, -3}}}}});
    cases.push_back({"flipped face", j, ramp, sideways, 0.01});
  }
  for (const Case& c : cases) {
    auto scene = build(c.scene);
    const int mi = mesh_index(*scene, "card");
    const Vec3f pivot = centre(scene->meshes[size_t(mi)]);
    const Estimate fd = finite_difference(*scene, mi, pivot, c.adjoint, c.dir, c.h, 48, 16);
    const GeometryEstimate ge = geometry_derivative(*scene, mi, pivot, c.adjoint, c.dir, 16);
    const double z = z_score(ge.total, fd);
    INFO(c.what << ": total " << ge.total.mean << " ± " << ge.total.stderr_ << " (primary " << ge.primary
                << ", interior " << ge.interior << ", secondary " << ge.secondary << "), finite differences " << fd.mean
                << " ± " << fd.stderr_ << ", z " << z);
    CHECK(std::abs(z) < 4);
    CHECK(std::abs(z_score(Estimate{0.0, 0.0}, fd)) > 4);
    CHECK(std::abs(z_score(Estimate{-ge.total.mean, ge.total.stderr_}, fd)) > 4);
  }
}

TEST_CASE("a one-sided surface seen from its back reflects nothing, and has no derivative", "[boundary]") {
  // The shadow scene seen from below its floor, made one-sided: the camera sees the floor's back
  // (black), so moving the blocker or the light changes nothing; every term must be exactly 0.
  nlohmann::json j = shadow_scene(3);
  j["materials"]["white"]["two_sided"] = false;
  j["cameras"][0]["origin"] = {0, -1.5, 1};
  j["cameras"][0]["target"] = {0, 0, 0};
  auto scene = build(j);
  const Image ones = constant_adjoint(1.f);
  for (const char* name : {"blocker", "light"}) {
    const int mi = mesh_index(*scene, name);
    PathGeometryOptions po;
    po.spp = 2;
    po.meshes = {mi};
    po.edge_samples = 4;
    const GeometryGradient g = path_geometry_gradient(*scene, ones, po);
    double norm = 0;
    for (const Vec3d& v : g.vertices[0]) norm += length(v);
    INFO(name);
    CHECK(norm == 0.0);
  }
}

TEST_CASE("the taped oracle and the closed-form pull-back give the same path derivatives",
          "[boundary][interior][taped]") {
  // Same paths, same edge samples: the taped mode differs only in how each path's derivative is
  // pulled back (a tape of the whole path in float, reverse-mode AD of the same log-factor templates
  // and of each hit as a function of the previous one, vs moving_hit_adjoint and duals in double).
  // The Cornell box (depth 3, interreflections, an emitter moving), the smooth dome (vertex
  // normals), and a moving camera.
  struct Case {
    const char* what;
    nlohmann::json scene;
    std::vector<std::string> meshes;
    bool camera_moves;
  };
  const Image ones = constant_adjoint(1.f);
  for (const Case& c : {Case{"cornell", cornell_scene(3), {"cube", "sphere", "light"}, false},
                        Case{"dome", dome_scene(), {"dome", "light"}, false},
                        Case{"cornell, camera moving", cornell_scene(3), {}, true}}) {
    auto scene = build(c.scene);
    PathGeometryOptions po;
    po.spp = 2;
    po.seed = 4242;
    po.camera_moves = c.camera_moves;
    for (const std::string& m : c.meshes) po.meshes.push_back(mesh_index(*scene, m));
    if (c.camera_moves)
      for (size_t i = 0; i < scene->meshes.size(); ++i) po.meshes.push_back(int(i));
    for (bool boundary : {false, true}) {
      po.boundary = boundary;
      po.taped = false;
      const GeometryGradient closed = path_geometry_gradient(*scene, ones, po);
      po.taped = true;
      const GeometryGradient taped = path_geometry_gradient(*scene, ones, po);
      double largest = 0, worst = 0;
      size_t nonzero = 0;
      auto compare = [&](const Vec3d& x, const Vec3d& y) {
        largest = std::max({largest, std::abs(x.x), std::abs(x.y), std::abs(x.z)});
        worst = std::max({worst, std::abs(x.x - y.x), std::abs(x.y - y.y), std::abs(x.z - y.z)});
        nonzero += x.x != 0 || x.y != 0 || x.z != 0;
      };
      REQUIRE(closed.vertices.size() == taped.vertices.size());
      for (size_t k = 0; k < closed.vertices.size(); ++k) {
        for (size_t i = 0; i < closed.vertices[k].size(); ++i) compare(closed.vertices[k][i], taped.vertices[k][i]);
        for (size_t i = 0; i < closed.normals[k].size(); ++i) compare(closed.normals[k][i], taped.normals[k][i]);
      }
      if (c.camera_moves) {  // the camera fields are defined (complete) only then
        compare(closed.camera_origin, taped.camera_origin);
        compare(closed.camera_rotate, taped.camera_rotate);
      }
      INFO(c.what << (boundary ? ", with the secondary term" : ", interior only") << ": " << nonzero
                  << " non-zero vectors, largest component " << largest << ", largest difference " << worst);
      CHECK(nonzero > 10);
      CHECK(largest > 0);
      CHECK(worst <= 1e-4 * largest);
      if (boundary) {
        // The comparison has teeth: the taped oracle without the interior factors (the boundary
        // term's share only) is far from the full closed-form derivative.
        po.interior = false;
        const GeometryGradient partial = path_geometry_gradient(*scene, ones, po);
        po.interior = true;
        double off = 0;
        for (size_t k = 0; k < closed.vertices.size(); ++k)
          for (size_t i = 0; i < closed.vertices[k].size(); ++i)
            off = std::max(off, length(closed.vertices[k][i] - partial.vertices[k][i]));
        CHECK(off > 1e-2 * largest);
      }
    }
  }
}
