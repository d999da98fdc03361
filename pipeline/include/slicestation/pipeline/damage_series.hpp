#pragma once
/// Damage in the context of its series (issue 18, item 5): sections of one brain arrive in
/// order, and anatomy that looks like damage (an enlarged ventricle, an opened fissure)
/// persists over neighbouring sections while a tear does not. A region found at the same atlas
/// place in the already registered neighbours of the same run is less likely damage.
///
/// Units: polygons in atlas pixels of one atlas (the sections' registrations map into the same
/// atlas grid: the slices of one stack share one pixel grid, so an atlas pixel means the same
/// left-right and dorso-ventral place in every slice). Threading: pure functions, re-entrant.
///
/// Only gaps (Tear, Missing) take part: anatomy that looks like damage is glass where the atlas
/// expects tissue (a ventricle wider than the atlas's, a fissure opened); a detached fragment or
/// a fold is no anatomy.

#include "slicestation/pipeline/damage.hpp"
#include "slicestation/pipeline/registration.hpp"

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
    /// registered neighbours. 6 px of 25 um: the real series' measured disagreement of two
    /// registrations of one section (slst_bench_consistency, median (section, warp) RMS without
    /// gross failures 5.4-7.2 atlas px; docs/registration.md).
    double slackAtlasPx = 6.0;
    /// How many earlier sections are looked at (live, the station has only those). Persistence
    /// is the share of this many, so a section with fewer earlier ones gets less context: the
    /// first section of a run none, the second at most half.
    int window = 2;
    /// Anatomy is continuous along the cutting axis: a place counts as persistent over the
    /// earlier sections only as far as they show it without a break from the nearest one on (a
    /// gap in the section two back but not in the one just before is no anatomy carried
    /// through). Off: any of the neighbours counts (for neighbours on both sides, each the
    /// nearest of its side).
    bool contiguous = true;
};

/// The share of `neighbours` (each one section's regions in atlas px, nearest first) with damage
/// at the same place as `region` (atlas px), out of max(neighbours, params.window); with
/// params.contiguous only those from the nearest on up to the first that does not: 0 when there
/// are none or the region is empty.
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

/// The section's gaps (Tear, Missing) as outlines in atlas pixels, parallel to `reg.damage`
/// (other kinds, and regions of fewer than 3 points, give an empty outline). Each outline is
/// subdivided to `maxSegmentPx` (full-resolution px) before it is mapped through the
/// registration (affine and warp), so a curved mapping bends it. A region that carries its
/// `atlasOutline` (found against another map than the registration's) gives that.
AtlasDamageOutlines atlasDamageOutlines(const Registration& reg, double maxSegmentPx = 4.0);
/// One region's outline mapped through `reg` (its polygon subdivided to `maxSegmentPx`); empty
/// for kinds without one (only tears and missing tissue are compared across sections).
std::vector<cv::Point2f> atlasDamageOutline(const Registration& reg, const DamageRegion& region,
                                            double maxSegmentPx = 4.0);

/// The glass inside `tissue` (CV_8U: its closed holes) where `expectedTissue` (CV_8U, the
/// atlas's tissue in the section frame, ventricles left out) expects tissue beyond `slackPx`
/// (eroded by a disc of that radius, as tissueDamage takes the registration slack): a ventricle
/// wider than the atlas's, a tear; not a ventricle the atlas has, nor a cut open to the outside.
cv::Mat glassWhereTissueIsExpected(const cv::Mat& tissue, const cv::Mat& expectedTissue,
                                   int slackPx);

/// The outlines of the pieces of `glass` (CV_8U, at the working size of `reg`:
/// Registration::workingScale) of at least `minAreaPx` working px, taken to full-resolution px,
/// subdivided to `maxSegmentPx` and mapped through `reg` into atlas px. The registration passes
/// glassWhereTissueIsExpected (Registration::glassAtlas).
std::vector<std::vector<cv::Point2f>> glassOutlines(const Registration& reg, const cv::Mat& glass,
                                                    double minAreaPx, double maxSegmentPx = 4.0);

/// What a registered section shows the sections after it in the series context (atlas px).
struct SectionShown {
    AtlasDamageOutlines gaps; ///< its gaps (atlasDamageOutlines)
    AtlasDamageOutlines
        glass; ///< its glass where its atlas expects tissue (Registration::glassAtlas)
    bool operator==(const SectionShown&) const = default;
};

/// The section's gaps and glass for the sections after it (`maxSegmentPx` as for
/// atlasDamageOutlines).
SectionShown shownInSeries(const Registration& reg, double maxSegmentPx = 4.0);

/// The damage decision of a registered section again, with its series context: sets each gap's
/// persistence among `earlier` (what the run's already registered sections show, nearest first;
/// at most params.window are used), then decideDamage, and updates reg.damageScore,
/// damageVerdict and damaged. A gap counts the earlier sections' gaps at its place; a band along
/// a ventricle's lumen (DamageRegion::alongVentricle: the section's ventricle wider than the
/// atlas's, or its wall torn along its length) also counts their glass where their atlas expects
/// tissue, whatever their own rules made of it: a ventricle wider than the atlas's over several
/// sections is anatomy carried through, though one section's rules left it out (as a band
/// reaching the midline, or by its twin) and the next's did not. A wedge torn away from a lumen
/// is no band and is not excused by a neighbour's wide ventricle; a ventricle no wider than the
/// atlas's shows no such glass. \return the decision.
DamageDecision judgeInSeries(Registration& reg, const std::vector<SectionShown>& earlier,
                             const DamageParams& damageParams, const SeriesContextParams& params);

} // namespace slicestation::pipeline
