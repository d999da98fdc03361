#pragma once
// ../shared/sections/abba-gerbi-series for every test and benchmark that reads it: the rows of its
// sections.csv, and the atlas plane of a section at its curated position and ABBA's tilt.
#include "abba_frame.hpp"
#include "slicestation/core/csv.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"

#include <opencv2/core.hpp>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace slicestation::testing_abba {

/// One row of sections.csv: section,file,width_px,height_px,um_per_px,abba_position_mm,...
struct GerbiRow {
    int number = 0;     ///< section
    std::string file;   ///< the thumbnail, relative to the series' folder
    double umPerPx = 0; ///< the thumbnail's pixel size
    double abbaMm = 0;  ///< abba_position_mm (ABBA's frame: ccfUmFromAbbaMm)
};

/// The rows of `dir`/sections.csv in its order, the header and rows of fewer than six fields
/// left out. \return NotFound when the file cannot be read, parseCsv's InvalidArgument.
inline core::Result<std::vector<GerbiRow>> readGerbiRows(const std::filesystem::path& dir) {
    const auto path = dir / "sections.csv";
    std::ifstream in(path);
    if (!in)
        return core::makeError(core::ErrorCode::NotFound, path.string());
    std::stringstream text;
    text << in.rdbuf();
    auto records = core::parseCsv(text.str(), path.string());
    if (!records)
        return records.error();
    std::vector<GerbiRow> rows;
    for (std::size_t i = 1; i < records->size(); ++i) {
        const auto& f = (*records)[i].fields;
        if (f.size() < 6)
            continue;
        rows.push_back({std::stoi(f[0]), f[1], std::stod(f[4]), std::stod(f[5])});
    }
    return rows;
}

/// The labels of the 25 um QuickNII annotation (`annotation25`, annotation_25_quicknii.nrrd) on
/// a section's plane, 25 um per px: at `abbaMm` along AP and leant as ABBA sliced the series.
/// ABBA's position is along AP from the front of the 10 um volume (voxel centres at 5 + 10 i um
/// from the front face); the atlas frame here starts at the 25 um volume's first voxel centre,
/// 12.5 um from the front face. ABBA's slicing angles (README): rotationX 0.042 rad about the
/// left-right axis leans the normal toward dorso-ventral (rows), rotationY 0.0015 rad toward
/// left-right (columns). \return planeGeometry's and sampleLabels' errors.
inline core::Result<cv::Mat> gerbiPlaneLabels(const core::Volume& annotation25, double abbaMm) {
    constexpr double kPi = 3.14159265358979323846;
    pipeline::CuttingPlane plane;
    plane.orientation = pipeline::PlaneOrientation::Coronal;
    plane.positionUm = ccfUmFromAbbaMm(abbaMm) - 7.5;
    plane.tiltRowsDeg = 0.042 * 180 / kPi;
    plane.tiltColumnsDeg = 0.0015 * 180 / kPi;
    plane.umPerPx = 25;
    auto geo = pipeline::planeGeometry(annotation25, pipeline::VolumeAxes::QuickNii, plane);
    if (!geo)
        return geo.error();
    return pipeline::sampleLabels(annotation25, pipeline::VolumeAxes::QuickNii, *geo);
}

} // namespace slicestation::testing_abba
