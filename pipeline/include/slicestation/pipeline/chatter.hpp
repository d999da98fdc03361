#pragma once

#include "slicestation/pipeline/damage.hpp"

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// Knife chatter: the knife vibrating as it cuts leaves the section's thickness swinging with a
/// steady period along the cut, so the stain's level swings with it in parallel bands. Tissue's
/// own texture (cells, layers, tracts) has no single period and direction shared across the
/// section.
///
/// The section's level relative to its local mean (a Gaussian of DamageParams::chatterLevelFrac
/// of the brain width) is cut into square tiles about DamageParams::chatterTileFrac of the width
/// wide (a power of two, overlapping by half, at least 90% on tissue away from the edge); each
/// tile's strongest spatial frequency with a period in DamageParams::chatterPeriodFrac (the
/// Hann-windowed DFT) is its peak, and the peak's amplitude its swing (0.1: the thickness
/// swinging by 10% about its mean). Tiles whose swing reaches DamageParams::chatterSwing and
/// whose peaks are one frequency (within one DFT bin, either sign) form one pattern; the largest
/// pattern of at least DamageParams::chatterTiles tiles, and at least
/// DamageParams::chatterDominance of all the tiles that swing as much, is chatter: one Chatter
/// region, the hull of those tiles' tissue (areaPx, share: the tiles' tissue; levelShare: their
/// mean swing; thicknessPx: the period in px). Empty when none (or chatterTiles is 0).
/// `grey`: CV_32F, tissue bright; `tissueMask`: CV_8U of its size.
std::vector<DamageRegion> chatterBands(const cv::Mat& grey, const cv::Mat& tissueMask,
                                       double brainWidthPx, const DamageParams& params);

} // namespace slicestation::pipeline
