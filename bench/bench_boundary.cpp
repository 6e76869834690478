// Cost of the primary-visibility boundary term (engine/integrators/boundary.h) against the primal
// render of the same scene and camera, in one process:
//   bench_boundary SCENE --spp S --edge-samples N [--secondary-spp K] [--resolution WxH]
// renders at S spp (timed), then computes the boundary term of every mesh's vertices for the
// adjoint image of ones with N edge samples (timed twice, to show the spread; each edge sample
// traces two paths), and the same with one sample (the cost of building the candidate-edge
// table), then the secondary term with K camera paths per pixel (when K > 0), and prints one JSON
// line: times, candidate edges, their projected length, triangles, peak RSS (getrusage).
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "engine/core/errors.h"
#include "engine/integrators/boundary.h"
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
    std::fprintf(stderr, "usage: bench_boundary SCENE --spp S --edge-samples N [--resolution WxH]\n");
    return 2;
  }
  int spp = 16, width = 0, height = 0, secondary_spp = 0;
  uint64_t samples = 0;
  for (int i = 2; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--spp") spp = std::atoi(argv[i + 1]);
    if (a == "--edge-samples") samples = std::strtoull(argv[i + 1], nullptr, 10);
    if (a == "--resolution") std::sscanf(argv[i + 1], "%dx%d", &width, &height);
    if (a == "--secondary-spp") secondary_spp = std::atoi(argv[i + 1]);
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
    BoundaryOptions bo;
    bo.samples = samples;
    double times[2];
    GeometryGradient g;
    for (double& t : times) {
      t0 = std::chrono::steady_clock::now();
      g = primary_boundary_gradient(*scene, ones, bo);
      t = seconds_since(t0);
    }
    // The candidate-edge table alone: the same call with one sample.
    bo.samples = 1;
    t0 = std::chrono::steady_clock::now();
    primary_boundary_gradient(*scene, ones, bo);
    const double setup = seconds_since(t0);
    double secondary = 0;
    if (secondary_spp > 0) {
      PathGeometryOptions so;
      so.spp = secondary_spp;
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
        "{\"width\": %d, \"height\": %d, \"spp\": %d, \"primal_seconds\": %.4f, \"edge_samples\": %llu, "
        "\"boundary_seconds\": [%.4f, %.4f], \"edge_table_seconds\": %.4f, \"candidate_edges\": %d, "
        "\"projected_edge_length_px\": %.1f, \"triangles\": %zu, \"secondary_spp\": %d, \"secondary_seconds\": %.4f, "
        "\"peak_rss_mb\": %.1f}\n",
        cam.width, cam.height, spp, primal, (unsigned long long)g.samples, times[0], times[1], setup, g.edges,
        g.edge_length, triangles, secondary_spp, secondary, double(ru.ru_maxrss) / 1024.0);
    (void)image;
  } catch (const InputError& e) {
    std::fprintf(stderr, "bench_boundary: %s\n", e.what());
    return 2;
  }
  return 0;
}
