#pragma once
/// Runs the peer, elastix (affine then B-spline, Advanced Mattes mutual information), on a case:
/// the section is the fixed image, the atlas template plane the moving image; landmarks are
/// mapped with transformix. Used only by the benchmark.

#include <opencv2/core.hpp>

#include <filesystem>
#include <string>
#include <vector>

namespace slicestation::bench {

/// True when `elastix` and `transformix` are on PATH.
bool elastixAvailable();

struct ElastixInput {
    cv::Mat fixed;             ///< section, CV_32F grey
    double fixedSpacingUm = 1; ///< section pixel size given to elastix (the calibration a user has)
    cv::Mat moving;            ///< template plane, CV_32F
    double movingSpacingUm = 100;
    double movingOriginUm = 0;       ///< physical position of moving pixel (0,0)'s centre
    std::vector<cv::Point2d> points; ///< section pixels to map
};

struct ElastixOutput {
    bool ok = false;
    std::string error;
    std::vector<cv::Point2d> mappedUm; ///< physical positions in the moving image, micrometres
    double seconds = 0;
};

/// Writes the inputs runElastix uses into `workDir` (fixed.mha, moving.mha, affine.txt,
/// bspline.txt, points.txt), so elastix and transformix can also be timed as whole processes:
///   elastix -f fixed.mha -m moving.mha -p affine.txt -p bspline.txt -out DIR -threads 1
///   transformix -def points.txt -tp DIR/TransformParameters.1.txt -out DIR -threads 1
void writeElastixInputs(const ElastixInput& input, const std::filesystem::path& workDir);

ElastixOutput runElastix(const ElastixInput& input, const std::filesystem::path& workDir);

} // namespace slicestation::bench
