#include "engine/io/plot.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "engine/io/image_io.h"

namespace bl {

namespace {

// 3×5 glyphs, row-major bits from the top-left (bit 14 = top-left pixel).
int glyph_bits(char c) {
  switch (c) {
    case '0':
      return 0b111101101101111;
    case '1':
      return 0b010110010010111;
    case '2':
      return 0b111001111100111;
    case '3':
      return 0b111001111001111;
    case '4':
      return 0b101101111001001;
    case '5':
      return 0b111100111001111;
    case '6':
      return 0b111100111101111;
    case '7':
      return 0b111001001001001;
    case '8':
      return 0b111101111101111;
    case '9':
      return 0b111101111001111;
    case '.':
      return 0b000000000000010;
    case '-':
      return 0b000000111000000;
    case '+':
      return 0b000010111010000;
    case 'e':
      return 0b000111101110011;
    default:
      return 0;
  }
}

struct Canvas {
  Image img;
  Canvas(int w, int h) : img(w, h, 3) { std::fill(img.data.begin(), img.data.end(), 1.f); }
  void dot(int x, int y, float r, float g, float b) {
    if (x < 0 || y < 0 || x >= img.width || y >= img.height) return;
    img.at(x, y, 0) = r, img.at(x, y, 1) = g, img.at(x, y, 2) = b;
  }
  void line(double x0, double y0, double x1, double y1, float r, float g, float b) {
    int steps = int(std::max(std::abs(x1 - x0), std::abs(y1 - y0))) + 1;
    for (int i = 0; i <= steps; ++i) {
      double t = double(i) / steps;
      int x = int(std::lround(x0 + (x1 - x0) * t)), y = int(std::lround(y0 + (y1 - y0) * t));
      dot(x, y, r, g, b);
      dot(x, y + 1, r, g, b);
    }
  }
  void text(int x, int y, const std::string& s, int scale = 2) {
    for (char c : s) {
      int bits = glyph_bits(c);
      for (int row = 0; row < 5; ++row)
        for (int col = 0; col < 3; ++col)
          if (bits & (1 << (14 - (row * 3 + col))))
            for (int a = 0; a < scale; ++a)
              for (int b = 0; b < scale; ++b) dot(x + col * scale + a, y + row * scale + b, 0.1f, 0.1f, 0.1f);
      x += 4 * scale;
    }
  }
};

std::string label(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3g", v);
  return buf;
}

}  // namespace

void write_line_plot(const std::string& path, const PlotSeries& s, bool log_y, const std::string&) {
  const int W = 640, H = 400, left = 90, right = 20, top = 20, bottom = 40;
  Canvas c(W, H);
  if (s.x.empty()) {
    write_image(path, c.img);
    return;
  }
  auto ty = [&](double y) { return log_y ? std::log10(std::max(y, 1e-30)) : y; };
  double x_min = *std::min_element(s.x.begin(), s.x.end()), x_max = *std::max_element(s.x.begin(), s.x.end());
  double y_min = 1e300, y_max = -1e300;
  for (double y : s.y) y_min = std::min(y_min, ty(y)), y_max = std::max(y_max, ty(y));
  if (x_max <= x_min) x_max = x_min + 1;
  if (y_max <= y_min) y_max = y_min + 1;
  auto px = [&](double x) { return left + (x - x_min) / (x_max - x_min) * (W - left - right); };
  auto py = [&](double y) { return H - bottom - (ty(y) - y_min) / (y_max - y_min) * (H - top - bottom); };
  // Axes and ticks with labels.
  c.line(left, top, left, H - bottom, 0, 0, 0);
  c.line(left, H - bottom, W - right, H - bottom, 0, 0, 0);
  for (int i = 0; i <= 4; ++i) {
    double fy = y_min + (y_max - y_min) * i / 4.0;
    double yy = H - bottom - (fy - y_min) / (y_max - y_min) * (H - top - bottom);
    c.line(left - 5, yy, left, yy, 0, 0, 0);
    c.text(4, int(yy) - 5, label(log_y ? std::pow(10.0, fy) : fy));
    double fx = x_min + (x_max - x_min) * i / 4.0;
    c.line(px(fx), H - bottom, px(fx), H - bottom + 5, 0, 0, 0);
    c.text(int(px(fx)) - 10, H - bottom + 10, label(fx));
  }
  for (size_t i = 1; i < s.x.size(); ++i)
    c.line(px(s.x[i - 1]), py(s.y[i - 1]), px(s.x[i]), py(s.y[i]), 0.1f, 0.3f, 0.8f);
  write_image(path, c.img);
}

}  // namespace bl
