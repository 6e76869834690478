#pragma once
// Gradient runs shared by `backlight grad`, `backlight check`, the optimizer and the tests.
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "engine/integrators/loss.h"
#include "engine/integrators/render.h"

namespace bl {

enum class GradientMethod { Prb, Rb, Taped };
GradientMethod parse_method(const std::string& name);
const char* method_name(GradientMethod m);

struct GradientRequest {
  GradientMethod method = GradientMethod::Prb;
  LossType loss = LossType::L2;
  const Image* target = nullptr;         // loss mode
  const Image* adjoint_image = nullptr;  // linear functional F = Σ a·I instead of a loss
  PassOptions pass;                      // camera, spp, seed of the primal (loss) render
  uint64_t adjoint_seed = 0;             // seed of the adjoint pass (equal: exact derivative)
  size_t memory_budget = 0;              // taped mode only: bytes (0 = 80% of physical memory)
  // Add to the grad buffers instead of zeroing them first. Under MPI the gradient is then this
  // rank's share: the caller sums it over ranks (dist::reduce_gradients) after its last pass.
  bool accumulate = false;
  // Geometry parameters (poses, vertex positions, camera pose): camera paths per pixel of their
  // interior and secondary-visibility terms, and primary edge samples per pixel (0 = pass.spp).
  int geometry_spp = 0;
  int edge_samples = 4;  // secondary-visibility edge samples per path vertex
};

struct GradientResult {
  double loss = 0;  // the loss, or F for an adjoint image
  Image image;      // the primal render the loss was computed on
  double primal_seconds = 0, adjoint_seconds = 0;
  // taped mode: the tape (16-byte entries) and what --memory-budget counts (each entry and its
  // float adjoint slot of the reverse sweep)
  uint64_t tape_bytes = 0, tape_entries = 0, tape_budget_bytes = 0;
  // Per MPI rank (one entry on one process), when known: peak RSS, and seconds in MPI calls.
  std::vector<double> peak_rss_bytes, mpi_seconds;
};

// Computes the gradient into the ParamStore's grad buffers (zeroed first) for the parameters
// marked requires_grad. Geometry parameters (ParamStore::wants_geometry) take the primary- and
// secondary-visibility boundary terms and the interior term (boundary.h, interior.h) of the image
// adjoint δI, chained into poses, vertex positions and the camera's pose (not in the taped mode). When adjoint_seed ==
// seed, the primal render and the adjoint pass are fused: each pixel is rendered once, its loss gradient taken, and its
// paths replayed. Under MPI every rank calls it; the pixels are split among them and, unless request.accumulate, the
// gradient is summed over ranks before it returns (image and loss are whole on every rank).
GradientResult compute_gradient(Scene& scene, const GradientRequest& request);

// The geometry part of a gradient: adds dF/dθ for F = ⟨adjoint, I⟩ into the grad buffers of the
// geometry parameters that require it (compute_gradient calls it on rank 0).
void add_geometry_gradient(Scene& scene, const Image& adjoint, const GradientRequest& request);
// Refuses (InputError, one line) views whose geometry gradient no term estimates: a rotating camera
// with an environment map in view, a near plane cutting a moving triangle (any, when the camera
// moves) inside the frustum.
void check_geometry_view(const Scene& scene, int camera);
// Throws (InputError naming the parameter) when a gradient that is wanted holds inf or NaN (float
// overflow). compute_gradient checks its result; a caller that accumulates passes (rq.accumulate)
// or sums over MPI ranks checks the sum.
void check_gradients_finite(const ParamStore& params);

// One row of a directional-derivative check.
struct CheckRow {
  double adjoint = 0;            // ⟨∇loss, v⟩ from the adjoint pass (mean over the seeds)
  double finite_difference = 0;  // (loss(θ+εv) − loss(θ−εv)) / 2ε, primal renders at the same seed (mean)
  double relative_error = 0;     // |adjoint − finite difference| / |finite difference|, of the means
  // |adjoint − finite difference| / the RMS over all directions of the finite differences (means):
  // the verdict's error (summarize_check). A direction whose derivative is tiny (v nearly
  // orthogonal to the gradient) has a large relative_error from the finite difference's own
  // truncation and rounding; against the typical directional derivative it does not.
  double rms_relative_error = 0;
  // Over several seeds: the standard errors of the two means, and the z score of their paired
  // differences (adjoint − finite difference at each seed); NaN for one seed.
  double adjoint_stderr = 0, fd_stderr = 0, z = std::numeric_limits<double>::quiet_NaN();
  double difference_stderr = 0;  // of the paired differences' mean
};

// The |z| a check over `seeds` seeds accepts: the two-sided 4σ tail of a normal (p = 6.3e-5) under
// Student's t with seeds − 1 degrees of freedom, since z divides by an estimated standard error
// (the normal's 4 let a correct gradient fail 15.5% of 2-seed checks, 2.9% of 4-seed ones).
// 10050 at 2 seeds (a check that cannot fail: its resolution says so), 32.6 at 4, 8.47 at 8, 5.48
// at 16, 4.29 at 64, → 4.
double check_z_threshold(int seeds);
// P(|T| ≥ t) for Student's t with dof degrees of freedom.
double student_t_two_sided_tail(double t, double dof);

// The verdict on a check's rows (the CLI's and Python's). A row passes when its rms_relative_error
// is within `tolerance`, or, over several seeds, when |z| < check_z_threshold(seeds). With one
// seed, the direction with the largest |fd_d| (≥ the RMS) fails any adjoint off by a factor 1 + r
// with |r| > tolerance. Over seeds, row d fails an error e_d of the adjoint's derivative along v_d
// once |e_d| exceeds both threshold·(standard error of the paired differences) and tolerance·RMS:
// `resolution[d]` is that bound over the RMS (NaN for one seed), `resolution_overall` the largest
// over the rows, and a pass is inconclusive when some direction could not have seen an error of
// 25% of the RMS. Every direction must resolve it: an error in elements that only some directions
// move (a sign error in one element whose steps make the finite differences noisy) would pass
// where the best-resolved direction barely moves them (helper-40: 15% of such checks said `ok`
// when the best direction decided). An adjoint off by a factor 1 + r, |r| > resolution_overall,
// fails in the direction with the largest |fd_d|.
struct CheckSummary {
  double threshold = 4;  // the |z| accepted
  std::vector<bool> ok;
  std::vector<double> resolution;
  double resolution_overall = std::numeric_limits<double>::quiet_NaN();
  bool passed = true, inconclusive = false;
  // Both sides exactly 0 in every direction: the parameter does not reach this image (a camera
  // that is not rendered, a material no visible path meets, a density at exactly 0). That
  // compares nothing: no row passes.
  bool nothing_compared = false;
};
CheckSummary summarize_check(const std::vector<CheckRow>& rows, int seeds, double tolerance);

// For `directions` random directions v with i.i.d. standard-normal elements (seeded,
// reproducible; for a vertex positions buffer one draw per welded position, so a mesh's split
// copies of a vertex move together and it stays closed), steps ±eps·v, compares the adjoint with
// central differences at the same seed. Sampling distributions that depend on appearance
// parameters (environment importance sampling, medium majorants) are held fixed, so both sides
// differentiate the same estimator; a geometry parameter re-poses the scene for each render (the
// BVH and emitter tables follow the meshes). Steps are clamped into the parameter's valid range
// (the adjoint side uses the steps taken); an eps not smaller than the range's width is refused
// (InputError). With `seeds` > 1 both sides are averaged over the render seeds seed, seed + 1, …
// (the adjoint seed likewise): where sampling depends on the parameter (roughness, moving
// silhouettes) same-seed differences jump, and the check is on the expectation (CheckRow::z).
std::vector<CheckRow> directional_check(Scene& scene, const std::string& param, const GradientRequest& request,
                                        int directions, double eps, uint64_t direction_seed, int seeds = 1);
// directional_check's steps θ ± eps·v for parameter `handle` (the directions drawn as described
// above, clamped into the valid range), one pair per direction; throws InputError where a step
// is not finite or every element rounds back to θ.
struct CheckSteps {
  std::vector<std::vector<float>> plus, minus;
};
CheckSteps check_steps(const Scene& scene, int handle, int directions, double eps, uint64_t direction_seed);
// For a mesh's vertex positions parameter (handle), per vertex the first vertex at bitwise the same
// position (−0 as +0, as edges are welded): directional_check moves such copies together. Empty
// for any other parameter.
std::vector<uint32_t> positions_welding(const Scene& scene, int handle);
// The check's refusal of an eps not smaller than the width of parameter `p`'s valid range, for
// callers that validate before they print (directional_check makes it too).
void check_eps_range(const Param& p, double eps);

// Output helpers (atomic writes).
void write_gradient_outputs(const Scene& scene, const GradientRequest& request, const GradientResult& result,
                            const std::string& dir);
// Parameter values: images as EXR, grids as .vdb, .vol and a PNG sheet, the rest in params.json.
void dump_parameter_values(const Scene& scene, const std::string& dir);

}  // namespace bl
