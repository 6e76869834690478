#pragma once
// Minimal raster line plots written as PNG (loss curves), so results are pictures without a
// Python dependency at run time. Axis ticks are labelled with a built-in 3×5 pixel font.
#include <string>
#include <vector>

namespace bl {

struct PlotSeries {
  std::vector<double> x, y;
};

// Plots y against x (y on a log10 axis when `log_y`), 640×400, and writes it atomically.
void write_line_plot(const std::string& path, const PlotSeries& series, bool log_y, const std::string& title);

}  // namespace bl
