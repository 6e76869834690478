#pragma once
// Pictures of volume grids for people: a sheet of four panels side by side — the mid-slices
// z = Z/2 (x right, y up), y = Y/2 (x right, z up) and x = X/2 (z right, y up), and the maximum
// projection along z (x right, y up) — each scaled to the same height (nearest neighbour), 4-pixel
// gaps. Values map linearly from [0, vmax] to [0, 1] (grey for one channel, RGB for three), and
// the sheet is meant for an 8-bit PNG: its values are stored so that the PNG's code values are
// proportional to the grid's (see write_grid_sheet).
#include <string>
#include <vector>

#include "engine/io/image_io.h"

namespace bl {

struct GridView {
  const std::vector<float>* data = nullptr;  // [Z, Y, X, C], x fastest
  int x = 0, y = 0, z = 0, channels = 1;
};

// The sheet at panel height `height` (linear values in [0, 1] before the PNG's encoding).
Image grid_sheet(const GridView& grid, float vmax, int height = 128);
// Stacks sheets vertically (4-pixel gaps), e.g. target / initial / final.
Image stack_rows(const std::vector<Image>& rows);
// Writes a sheet (or a stack) as PNG so that code values are proportional to the values.
void write_grid_picture(const std::string& png_path, const Image& sheet);

}  // namespace bl
