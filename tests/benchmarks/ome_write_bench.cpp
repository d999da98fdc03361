// What the pyramid costs when a section image is written: the old layout (one page of deflate
// strips) against the OME-TIFF pyramid (512 px deflate tiles plus reduced levels in SubIFDs),
// for the sizes the station writes (one 1280 x 1024 field, stitched sections). Prints, per size,
// the median write time of each layout over --repeats writes, and the file sizes.
#include "slicestation/core/tiff_file.hpp"

#include <CLI/CLI.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

namespace {

using namespace slicestation;
namespace fs = std::filesystem;

/// A section-like 16-bit image: smooth tissue with noise (noise decides deflate's speed).
cv::Mat sectionLike(cv::Size size) {
    cv::Mat img(size, CV_16UC1);
    cv::randn(img, 3000, 300);
    cv::Mat blob = cv::Mat::zeros(size, CV_16UC1);
    cv::ellipse(blob, {size.width / 2, size.height / 2}, {size.width * 2 / 5, size.height / 3}, 0,
                0, 360, cv::Scalar(20000), -1);
    cv::GaussianBlur(blob, blob, {0, 0}, size.width / 50.0);
    return img + blob;
}

template <class Write> double medianMs(const fs::path& file, int repeats, Write write) {
    std::vector<double> ms;
    for (int r = 0; r < repeats; ++r) {
        fs::remove(file);
        const int fd = ::open(file.c_str(), O_RDWR | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
        const auto t0 = std::chrono::steady_clock::now();
        const bool ok = static_cast<bool>(write(fd));
        ms.push_back(
            std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0)
                .count());
        ::close(fd);
        if (!ok) {
            std::fprintf(stderr, "write failed\n");
            return -1;
        }
    }
    std::sort(ms.begin(), ms.end());
    return ms[ms.size() / 2];
}

} // namespace

int main(int argc, char** argv) {
    CLI::App app{"OME-TIFF write cost: strips against the tiled pyramid"};
    int repeats = 5;
    app.add_option("--repeats", repeats, "writes per layout and size")->check(CLI::Range(1, 100));
    std::vector<std::string> sizes{"1280x1024", "4000x3000", "8000x6000"};
    app.add_option("--sizes", sizes, "WxH ...");
    CLI11_PARSE(app, argc, argv);
    const fs::path dir =
        fs::temp_directory_path() / ("slst-ome-bench-" + std::to_string(::getpid()));
    fs::create_directories(dir);
    std::printf("| size (16-bit) | strips ms | pyramid ms | strips MB | pyramid MB | levels |\n");
    std::printf("|---|---|---|---|---|---|\n");
    for (const std::string& s : sizes) {
        int w = 0, h = 0;
        if (std::sscanf(s.c_str(), "%dx%d", &w, &h) != 2 || w < 16 || h < 16)
            return 2;
        const cv::Mat img = sectionLike({w, h});
        const core::TiffTags tags{"<OME/>", "bench", 1.0};
        const fs::path a = dir / "strips.tif", b = dir / "pyramid.tif";
        const double strips =
            medianMs(a, repeats, [&](int fd) { return core::writeTiffPage(fd, a, img, tags); });
        const double pyramid =
            medianMs(b, repeats, [&](int fd) { return core::writeTiffPyramid(fd, b, img, tags); });
        std::printf("| %dx%d | %.0f | %.0f | %.1f | %.1f | %zu |\n", w, h, strips, pyramid,
                    fs::file_size(a) / 1e6, fs::file_size(b) / 1e6,
                    core::tiffPyramidLevels(img.size(), 1024).size());
    }
    fs::remove_all(dir);
    return 0;
}
