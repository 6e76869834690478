// Cost of the geometry-gradient terms against the primal render and the appearance prb pass of the
// same scene and camera, in one process:
//   bench_boundary SCENE --spp S --geometry-spp K [--edge-samples E] [--resolution WxH] [--no-paths]
//                  [--scan]
// renders at S spp (timed), runs the prb adjoint pass for every appearance parameter at S spp
// (timed; the adjoint image is ones), then the primary boundary term of every mesh's vertices with
// K edge samples per pixel (timed twice, to show the spread; each traces two paths) and with one
// sample (the candidate-edge table alone), then on K camera paths per pixel the interior term
// alone and the secondary term alone (E edge samples per vertex, through the edge hierarchy or,
// with --scan, a scan of every edge per vertex; skipped with --no-paths), and
// prints one JSON line: times, candidate edges, triangles, peak RSS (getrusage).
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "engine/core/errors.h"
#include "engine/integrators/boundary.h"
#include "engine/integrators/gradient.h"
#include "engine/integrators/interior.h"
#include "engine/integrators/render.h"
#include "engine/scene/scene_load.h"

using namespace bl;

namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr,
                 "usage: bench_boundary SCENE --spp S --geometry-spp K [--edge-samples E] [--resolution WxH] "
                 "[--no-paths]\n");
    return 2;
  }
  int spp = 16, width = 0, height = 0, geometry_spp = 1, edge_samples = 4;
  bool paths = true, scan = false;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--no-paths") {
      paths = false;
      continue;
    }
    if (a == "--scan") {  // the secondary term without the edge hierarchy
      scan = true;
      continue;
    }
    if (i + 1 >= argc) break;
    if (a == "--spp")
      spp = std::atoi(argv[++i]);
    else if (a == "--geometry-spp")
      geometry_spp = std::atoi(argv[++i]);
    else if (a == "--edge-samples")
      edge_samples = std::atoi(argv[++i]);
    else if (a == "--resolution")
      std::sscanf(argv[++i], "%dx%d", &width, &height);
  }
  try {
    auto scene = load_scene(argv[1]);
    Camera& cam = scene->cameras[0];
    if (width > 0 && height > 0) {
      cam.width = width;
      cam.height = height;
      validate_camera(cam, argv[1]);
    }
    PassOptions po;
    po.spp = spp;
    po.progress = false;
    auto t0 = std::chrono::steady_clock::now();
    const Image image = render(*scene, po);
    const double primal = seconds_since(t0);
    Image ones(cam.width, cam.height, 3);
    for (float& v : ones.data) v = 1.f;
    // The appearance adjoint pass (prb, every appearance parameter), fused with its primal.
    scene->params.require_grad({});
    GradientRequest rq;
    rq.adjoint_image = &ones;
    rq.pass = po;
    t0 = std::chrono::steady_clock::now();
    compute_gradient(*scene, rq);
    const double prb = seconds_since(t0);

    BoundaryOptions bo;
    bo.samples = uint64_t(cam.width) * uint64_t(cam.height) * uint64_t(geometry_spp);
    double times[2];
    GeometryGradient g;
    for (double& t : times) {
      t0 = std::chrono::steady_clock::now();
      g = primary_boundary_gradient(*scene, ones, bo);
      t = seconds_since(t0);
    }
    bo.samples = 1;  // the candidate-edge table alone
    t0 = std::chrono::steady_clock::now();
    primary_boundary_gradient(*scene, ones, bo);
    const double setup = seconds_since(t0);
    double interior = 0, secondary = 0;
    if (paths) {
      PathGeometryOptions so;
      so.spp = geometry_spp;
      so.edge_samples = edge_samples;
      so.edge_hierarchy = !scan;
      so.boundary = false;
      t0 = std::chrono::steady_clock::now();
      path_geometry_gradient(*scene, ones, so);
      interior = seconds_since(t0);
      so.boundary = true;
      so.interior = false;
      t0 = std::chrono::steady_clock::now();
      path_geometry_gradient(*scene, ones, so);
      secondary = seconds_since(t0);
    }
    size_t triangles = 0;
    for (const Mesh& m : scene->meshes) triangles += m.triangle_count();
    rusage ru{};
    getrusage(RUSAGE_SELF, &ru);
    std::printf(
        "{\"width\": %d, \"height\": %d, \"spp\": %d, \"geometry_spp\": %d, \"edge_samples_per_vertex\": %d, "
        "\"primal_seconds\": %.4f, \"prb_seconds\": %.4f, \"boundary_seconds\": [%.4f, %.4f], "
        "\"edge_table_seconds\": %.4f, \"candidate_edges\": %d, \"projected_edge_length_px\": %.1f, "
        "\"triangles\": %zu, \"interior_seconds\": %.4f, \"secondary_seconds\": %.4f, \"peak_rss_mb\": %.1f}\n",
        cam.width, cam.height, spp, geometry_spp, edge_samples, primal, prb, times[0], times[1], setup, g.edges,
        g.edge_length, triangles, interior, secondary, double(ru.ru_maxrss) / 1024.0);
    (void)image;
  } catch (const InputError& e) {
    std::fprintf(stderr, "bench_boundary: %s\n", e.what());
    return 2;
  }
  return 0;
}
