#pragma once
/// Damage in the context of its series (issue 18, item 5): sections of one brain arrive in
/// order, and anatomy that looks like damage (an enlarged ventricle, an opened fissure)
/// persists over neighbouring sections while a tear does not. A region found at the same atlas
/// place in the already registered neighbours of the same run is less likely damage.
///
/// Units: polygons in atlas pixels of one atlas (the sections' registrations map into the same
/// atlas grid). Threading: pure functions, re-entrant.

#include "slicestation/pipeline/damage.hpp"

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// One section's damage regions as outlines in atlas pixels.
using AtlasDamageOutlines = std::vector<std::vector<cv::Point2f>>;

struct SeriesContextParams {
    /// A neighbour has a region at the same place when its regions, grown by the registration
    /// slack, cover at least this share of the region's atlas area.
    double samePlaceShare = 0.3;
    /// The registration slack in atlas pixels: how far the same anatomy may land apart in two
    /// registered neighbours (and how far it moves between two sections).
    double slackAtlasPx = 6.0;
};

/// The share of `neighbours` (each one section's regions in atlas px) with damage at the same
/// place as `region` (atlas px): 0 when there are none or the region is empty.
double persistenceAmong(const std::vector<cv::Point2f>& region,
                        const std::vector<AtlasDamageOutlines>& neighbours,
                        const SeriesContextParams& params);

/// Sets each region's DamageRegion::persistence from its atlas outline (`regionsAtlas`, parallel
/// to `regions`) and the neighbours' outlines, and returns the section's damage score again
/// (damageScore with the persistence applied). A region with no atlas outline keeps 0.
double applySeriesContext(std::vector<DamageRegion>& regions,
                          const AtlasDamageOutlines& regionsAtlas,
                          const std::vector<AtlasDamageOutlines>& neighbours, double brainWidthPx,
                          const DamageParams& damageParams, const SeriesContextParams& params);

} // namespace slicestation::pipeline
