#include "engine/io/grid_view.h"

#include <algorithm>

namespace bl {

namespace {
constexpr int kGap = 4;

// One panel: value(u, v) for u in [0, w), v in [0, h) (v up), scaled to `height` rows.
template <class F>
void draw_panel(Image& sheet, int x0, int w, int h, int height, int channels, float vmax, F&& value) {
  const int width = std::max(1, int(double(w) * height / h + 0.5));
  for (int py = 0; py < height; ++py)
    for (int px = 0; px < width; ++px) {
      const int u = std::min(w - 1, px * w / width), v = std::min(h - 1, (height - 1 - py) * h / height);
      for (int c = 0; c < 3; ++c)
        sheet.at(x0 + px, py, c) = std::clamp(value(u, v, std::min(c, channels - 1)) / vmax, 0.f, 1.f);
    }
}
int panel_width(int w, int h, int height) { return std::max(1, int(double(w) * height / h + 0.5)); }
}  // namespace

Image grid_sheet(const GridView& g, float vmax, int height) {
  if (!(vmax > 0.f)) vmax = 1.f;
  const std::vector<float>& d = *g.data;
  auto at = [&](int ix, int iy, int iz, int c) {
    return d[((size_t(iz) * size_t(g.y) + size_t(iy)) * size_t(g.x) + size_t(ix)) * size_t(g.channels) + size_t(c)];
  };
  const int widths[4] = {panel_width(g.x, g.y, height), panel_width(g.x, g.z, height), panel_width(g.z, g.y, height),
                         panel_width(g.x, g.y, height)};
  Image sheet(widths[0] + widths[1] + widths[2] + widths[3] + 3 * kGap, height, 3);
  int x0 = 0;
  draw_panel(sheet, x0, g.x, g.y, height, g.channels, vmax, [&](int u, int v, int c) { return at(u, v, g.z / 2, c); });
  x0 += widths[0] + kGap;
  draw_panel(sheet, x0, g.x, g.z, height, g.channels, vmax, [&](int u, int v, int c) { return at(u, g.y / 2, v, c); });
  x0 += widths[1] + kGap;
  draw_panel(sheet, x0, g.z, g.y, height, g.channels, vmax, [&](int u, int v, int c) { return at(g.x / 2, v, u, c); });
  x0 += widths[2] + kGap;
  draw_panel(sheet, x0, g.x, g.y, height, g.channels, vmax, [&](int u, int v, int c) {
    float m = 0.f;
    for (int iz = 0; iz < g.z; ++iz) m = std::max(m, at(u, v, iz, c));
    return m;
  });
  return sheet;
}

Image stack_rows(const std::vector<Image>& rows) {
  int width = 0, height = 0;
  for (const auto& r : rows) width = std::max(width, r.width), height += r.height;
  height += kGap * int(rows.size() > 0 ? rows.size() - 1 : 0);
  Image out(std::max(1, width), std::max(1, height), 3);
  int y0 = 0;
  for (const auto& r : rows) {
    for (int y = 0; y < r.height; ++y)
      for (int x = 0; x < r.width; ++x)
        for (int c = 0; c < 3; ++c) out.at(x, y0 + y, c) = r.at(x, y, std::min(c, r.channels - 1));
    y0 += r.height + kGap;
  }
  return out;
}

void write_grid_picture(const std::string& png_path, const Image& sheet) {
  // write_image encodes linear values as sRGB; pre-apply the inverse so code values are linear in
  // the grid's values.
  Image encoded = sheet;
  for (float& v : encoded.data) v = srgb_to_linear(v);
  write_image(png_path, encoded);
}

}  // namespace bl
