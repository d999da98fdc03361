#include "elastix_runner.hpp"

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <regex>
#include <sstream>

namespace slicestation::bench {
namespace {

void writeMha(const std::filesystem::path& path, const cv::Mat& img, double spacing,
              double origin) {
    CV_Assert(img.type() == CV_32F && img.isContinuous());
    std::ofstream f(path, std::ios::binary);
    f << "ObjectType = Image\nNDims = 2\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
      << "DimSize = " << img.cols << " " << img.rows << "\n"
      << "ElementSpacing = " << spacing << " " << spacing << "\n"
      << "Offset = " << origin << " " << origin << "\n"
      << "ElementType = MET_FLOAT\nElementDataFile = LOCAL\n";
    f.write(reinterpret_cast<const char*>(img.data), static_cast<std::streamsize>(img.total() * 4));
}

const char* kCommon = R"((FixedInternalImagePixelType "float")
(MovingInternalImagePixelType "float")
(FixedImageDimension 2)
(MovingImageDimension 2)
(UseDirectionCosines "true")
(Registration "MultiResolutionRegistration")
(Interpolator "BSplineInterpolator")
(ResampleInterpolator "FinalBSplineInterpolator")
(Resampler "DefaultResampler")
(FixedImagePyramid "FixedSmoothingImagePyramid")
(MovingImagePyramid "MovingSmoothingImagePyramid")
(Optimizer "AdaptiveStochasticGradientDescent")
(Metric "AdvancedMattesMutualInformation")
(NumberOfHistogramBins 32)
(ImageSampler "RandomCoordinate")
(NewSamplesEveryIteration "true")
(BSplineInterpolationOrder 1)
(FinalBSplineInterpolationOrder 3)
(DefaultPixelValue 0)
(WriteResultImage "false")
(HowToCombineTransforms "Compose")
)";

bool run(const std::string& cmd, std::string& err) {
    const int rc = std::system(cmd.c_str());
    if (rc != 0) {
        err = "command failed (" + std::to_string(rc) + "): " + cmd;
        return false;
    }
    return true;
}

} // namespace

bool elastixAvailable() {
    return std::system(
               "command -v elastix >/dev/null 2>&1 && command -v transformix >/dev/null 2>&1") == 0;
}

void writeElastixInputs(const ElastixInput& in, const std::filesystem::path& dir) {
    std::filesystem::create_directories(dir);
    writeMha(dir / "fixed.mha", in.fixed, in.fixedSpacingUm, 0.0);
    writeMha(dir / "moving.mha", in.moving, in.movingSpacingUm, in.movingOriginUm);
    {
        std::ofstream a(dir / "affine.txt");
        a << kCommon << R"((Transform "AffineTransform")
(AutomaticScalesEstimation "true")
(AutomaticTransformInitialization "true")
(AutomaticTransformInitializationMethod "CenterOfGravity")
(NumberOfResolutions 4)
(MaximumNumberOfIterations 500)
(NumberOfSpatialSamples 4096)
)";
        std::ofstream b(dir / "bspline.txt");
        // Control points every ~300 um: about the scale of the generator's smooth deformation.
        b << kCommon << R"((Transform "BSplineTransform")
(FinalGridSpacingInPhysicalUnits 300)
(GridSpacingSchedule 4 2 1)
(NumberOfResolutions 3)
(MaximumNumberOfIterations 500)
(NumberOfSpatialSamples 4096)
)";
        std::ofstream p(dir / "points.txt");
        p << "point\n" << in.points.size() << "\n";
        for (const auto& q : in.points)
            p << q.x * in.fixedSpacingUm << " " << q.y * in.fixedSpacingUm << "\n";
    }
}

ElastixOutput runElastix(const ElastixInput& in, const std::filesystem::path& dir) {
    ElastixOutput out;
    const auto t0 = std::chrono::steady_clock::now();
    writeElastixInputs(in, dir);
    const std::string d = dir.string();
    if (!run("elastix -f " + d + "/fixed.mha -m " + d + "/moving.mha -p " + d + "/affine.txt -p " +
                 d + "/bspline.txt -out " + d + " -threads 1 > " + d + "/elastix.out 2>&1",
             out.error))
        return out;
    if (!run("transformix -def " + d + "/points.txt -tp " + d + "/TransformParameters.1.txt -out " +
                 d + " -threads 1 > " + d + "/transformix.out 2>&1",
             out.error))
        return out;
    out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::ifstream res(dir / "outputpoints.txt");
    const std::regex re(R"(OutputPoint\s*=\s*\[\s*([-0-9.eE+]+)\s+([-0-9.eE+]+)\s*\])");
    std::string line;
    while (std::getline(res, line)) {
        std::smatch m;
        if (std::regex_search(line, m, re))
            out.mappedUm.emplace_back(std::stod(m[1].str()), std::stod(m[2].str()));
    }
    out.ok = out.mappedUm.size() == in.points.size();
    if (!out.ok)
        out.error = "transformix returned " + std::to_string(out.mappedUm.size()) + " points";
    return out;
}

} // namespace slicestation::bench
