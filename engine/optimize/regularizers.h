#pragma once
// Regularizers of the optimize job (`"regularizer"` in a parameter's entry): each adds weight ·
// ∂R/∂θ to the parameter's gradient and returns weight · R, which the job adds to the loss. Total
// variation is for images ([H, W, C]) and grids ([Z, Y, X, C]) (the job refuses it on other
// parameters; here they return 0); L1 is for any parameter.
#include "engine/core/params.h"

namespace bl {

// Total variation: R = mean over cells of sqrt(|∇θ|² + ε²), ε = 1e-3, with forward differences
// along every axis (clamped at the last cell), per channel.
double add_total_variation(Param& p, double weight);

// Sparsity: R = mean |θ| over the elements. A constant pull towards 0 that decides where the
// images constrain θ only weakly (e.g. empty space enclosed by a dense medium).
double add_l1(Param& p, double weight);

}  // namespace bl
