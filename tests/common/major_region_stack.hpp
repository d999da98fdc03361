#pragma once
// The coronal atlas stack the series benchmarks match real sections against: an annotation volume
// (Allen axes) cut every intervalUm from its front, each plane's labels collapsed to the major
// regions, and the features atlas matching compares a section with. One helper for every
// benchmark that builds it, so that each does not carry its own copy.
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::testing_atlas {

struct MajorRegionStack {
    std::vector<pipeline::AtlasSlice> slices;      ///< as cut: the fine labels, the geometry
    std::vector<cv::Mat> labels;                   ///< slices' labels collapsed (depth 8)
    double workUm = 0;                             ///< matchWorkUmPerPx of `labels`
    std::vector<pipeline::SliceFeatures> features; ///< one per slice, at its position
};

/// `volume` cut coronally every `intervalUm` from 0 at `umPerPx`, collapsed to the major regions
/// of `ontology`. \return sliceVolume's errors.
inline core::Result<MajorRegionStack> majorRegionStack(const core::Volume& volume,
                                                       const core::Ontology& ontology,
                                                       double intervalUm, double umPerPx) {
    auto slices =
        pipeline::sliceVolume(volume, pipeline::VolumeAxes::Allen,
                              {pipeline::PlaneOrientation::Coronal, 0, intervalUm, 0, 0, umPerPx});
    if (!slices)
        return slices.error();
    MajorRegionStack out;
    out.slices = std::move(*slices);
    for (const auto& s : out.slices)
        out.labels.push_back(
            pipeline::collapseLabels(s.labels, ontology, pipeline::majorRegionIds(), 8));
    out.workUm = pipeline::matchWorkUmPerPx(out.labels, umPerPx);
    for (std::size_t i = 0; i < out.labels.size(); ++i)
        out.features.push_back(pipeline::sliceFeatures(
            out.labels[i], umPerPx, out.slices[i].geometry.positionUm, out.workUm));
    return out;
}

} // namespace slicestation::testing_atlas
