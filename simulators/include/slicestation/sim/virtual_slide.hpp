#pragma once
/// A virtual microscope slide for the simulated camera: brain sections laid out on a grid at
/// known stage positions, either generated from the built-in atlas with the section generator
/// (with ground truth about which section lies where and what damage it carries) or loaded from
/// real section images (e.g. ../shared/sections).
///
/// Frames: the slide image's top-left pixel corner sits at stage position (originXUm,
/// originYUm); image x grows with stage X, image y with stage Y; umPerPx is the image's pixel
/// size. Section i sits in grid cell (i % columns, i / columns) of `pitch` µm squares, centred.
/// Threading: both functions are re-entrant. Blocking: CPU only (generation ~0.3 s per section
/// at 1250 px; loading is file I/O).

#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"

#include <opencv2/core/mat.hpp>

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

namespace slicestation::sim {

struct SlideSectionSpec {
    double apFraction = 0.5; ///< built-in atlas plane, 0 (front) .. 1 (back)
    std::string damage;      ///< "", "tear", "missing", "fragment"
    std::uint64_t seed = 1;  ///< generator seed (deformation, stain, damage placement)
};

struct VirtualSlideSpec {
    std::vector<SlideSectionSpec> sections;
    int columns = 4;
    double sectionPitchUm = 12'000; ///< centre-to-centre spacing
    double sectionWidthUm = 10'000; ///< nominal size of a generated section (its image patch;
                                    ///< the tissue spans about 75% of it)
    double umPerPx = 8.0;           ///< pixel size of the slide image
    double originXUm = 5'000,
           originYUm = 5'000; ///< stage position of the slide image's top-left corner
    bool brightfield = false; ///< false: fluorescence, CV_16UC1; true: CV_8UC3 BGR
    double marginUm = 1'000;  ///< glass around the grid
};

struct SlideSection {
    int index;                ///< position in the spec / image list
    hw::StagePosition centre; ///< stage position of the section's cell centre (z = 0)
    double widthUm, heightUm; ///< extent of its image patch
    double apFraction;        ///< the atlas plane it was generated from; -1 for a loaded image
    std::string damage;       ///< as requested; "" for a loaded image (unknown)
};

struct VirtualSlide {
    cv::Mat image; ///< CV_16UC1 (fluorescence) or CV_8UC3 BGR (brightfield, colour images)
    double umPerPx;
    double originXUm, originYUm;
    std::vector<SlideSection> sections;
};

/// Generates every section from builtinAtlasPlane(apFraction) with sim::generateSection
/// (damage painted by the generator) and lays them out on glass.
/// \return InvalidArgument naming the field (no sections, columns < 1, a size or pitch not
///         positive, sectionWidthUm > sectionPitchUm, a patch outside 300..10000 px after
///         scaling, apFraction outside [0, 1], an unknown damage kind); Internal (OpenCV).
core::Result<VirtualSlide> makeVirtualSlide(const VirtualSlideSpec& spec);

/// Real section images placed on a grid (cell i at column i % columns), each centred in its
/// `pitchUm` cell; the slide image is exactly the grid, origin (0, 0) (callers may move it by
/// setting originXUm/originYUm). Glass between the images takes the median level of the images'
/// borders. Grey images of any depth become CV_16UC1 (8-bit scaled by 257); two-channel images
/// (ABBA's DAPI + signal) keep channel 0; colour images make the slide CV_8UC3 BGR.
/// \return InvalidArgument (no images, columns < 1, a size not positive, an image larger than
///         its cell), or the error of core::readImage naming the file (NotFound, IoError,
///         Unsupported).
core::Result<VirtualSlide> loadVirtualSlide(const std::vector<std::filesystem::path>& images,
                                            double umPerPx, int columns, double pitchUm);

} // namespace slicestation::sim
