#pragma once
// The curated positions of ../shared/sections/abba-gerbi-series (sections.csv,
// abba_position_mm) in the CCF frame, for every test and benchmark that reads them.
//
// ABBA widens the atlas by 15% of its half-length at each end before it counts slicing
// positions from the front (its ReslicedAtlas); for CCFv3, 13.2 mm along AP, that is 0.99 mm
// before the volume's front face (docs/atlas.md, "The gerbi offset").

namespace slicestation::testing_abba {

/// How far before the CCF volume's front face ABBA's slicing positions start (um).
inline constexpr double kSlicingMarginUm = 0.15 * 13200 / 2;

/// abba_position_mm as um from the CCF volume's front face.
inline double ccfUmFromAbbaMm(double abbaMm) {
    return abbaMm * 1000 - kSlicingMarginUm;
}

} // namespace slicestation::testing_abba
