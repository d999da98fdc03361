#include "slicestation/pipeline/edges.hpp"

#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

namespace slicestation::pipeline {

double dominantEdgeThreshold(const cv::Mat& gradientMagnitude, const DominantEdgeParams& params) {
    CV_Assert(gradientMagnitude.type() == CV_32F);
    cv::Mat mag = gradientMagnitude.isContinuous() ? gradientMagnitude : gradientMagnitude.clone();
    const auto* v = mag.ptr<float>();
    const size_t n = mag.total();
    if (n < 2)
        return 0.0;

    // Only pixels with some gradient take part: flat glass would otherwise dominate the
    // histogram and Scott's rule alike.
    std::vector<float> vals;
    vals.reserve(n / 2);
    double maxV = 0;
    for (size_t i = 0; i < n; ++i) {
        if (v[i] > 1e-6f) {
            vals.push_back(v[i]);
            maxV = std::max<double>(maxV, v[i]);
        }
    }
    if (vals.size() < 16)
        return maxV;
    double mean = 0;
    for (float x : vals)
        mean += x;
    mean /= double(vals.size());
    double var = 0;
    for (float x : vals)
        var += (x - mean) * (x - mean);
    const double sd = std::sqrt(var / double(vals.size()));

    // Algorithm 1 line 3: Scott's rule, bin width h = 3.49 sigma N^(-1/3).
    const double h = std::max(1e-9, 3.49 * sd * std::pow(double(vals.size()), -1.0 / 3.0));
    const int bins = std::clamp(static_cast<int>(std::ceil(maxV / h)), 8, 100000);
    std::vector<int> count(bins, 0);
    std::vector<double> sum(bins, 0.0);
    for (float x : vals) {
        const int b = std::min(bins - 1, static_cast<int>(x / h));
        ++count[b];
        sum[b] += x;
    }
    // Line 4: the first k bins whose adjacent counts differ by at most s. Scanning starts at the
    // histogram's mode: below it counts rise from zero and can look "stable" in a sparse image.
    const int mode = static_cast<int>(std::max_element(count.begin(), count.end()) - count.begin());
    const double s = std::max(1.0, params.stableFraction * count[mode]);
    const int k = std::max(2, params.stableBins);
    for (int start = mode; start + k <= bins; ++start) {
        bool stable = true;
        for (int i = start; i + 1 < start + k && stable; ++i)
            stable = std::abs(count[i + 1] - count[i]) <= s;
        if (!stable)
            continue;
        double total = 0;
        int cnt = 0;
        for (int i = start; i < start + k; ++i) {
            total += sum[i];
            cnt += count[i];
        }
        // Line 5: K is the mean magnitude of the values in those bins.
        if (cnt > 0)
            return total / cnt;
        return (start + 0.5 * k) * h;
    }
    std::nth_element(vals.begin(), vals.begin() + static_cast<std::ptrdiff_t>(vals.size() * 9 / 10),
                     vals.end());
    return vals[vals.size() * 9 / 10];
}

cv::Mat dominantEdges(const cv::Mat& grey, const DominantEdgeParams& params) {
    CV_Assert(grey.type() == CV_32F);
    const int longSide = std::max(grey.rows, grey.cols);
    cv::Mat u8;
    grey.convertTo(u8, CV_8U, 255.0);
    // Algorithm 1 line 1: median then Gaussian smoothing.
    int wm = static_cast<int>(std::lround(params.medianFrac * longSide)) | 1;
    wm = std::max(5, wm); // a 3x3 median leaves speckle chains in noisy captures
    cv::Mat med;
    cv::medianBlur(u8, med, wm);
    const double sigma = std::max(1.0, params.sigmaFrac * longSide);
    cv::Mat smooth;
    cv::GaussianBlur(med, smooth, cv::Size(), sigma);

    cv::Mat dx, dy;
    cv::Sobel(smooth, dx, CV_16S, 1, 0, 3);
    cv::Sobel(smooth, dy, CV_16S, 0, 1, 3);
    cv::Mat fx, fy, mag;
    dx.convertTo(fx, CV_32F);
    dy.convertTo(fy, CV_32F);
    cv::magnitude(fx, fy, mag);
    const double high = std::max(1.0, dominantEdgeThreshold(mag, params));
    cv::Mat edges;
    cv::Canny(dx, dy, edges, params.lowRatio * high, high, true);
    const int minChain = static_cast<int>(params.minChainFrac * longSide);
    if (minChain > 1) {
        cv::Mat labels, stats;
        const int n = labelComponents(edges, labels, stats);
        std::vector<uchar> drop(static_cast<size_t>(n), 0);
        for (int i = 1; i < n; ++i)
            drop[i] = stats.at<int>(i, cv::CC_STAT_AREA) < minChain;
        for (int y = 0; y < edges.rows; ++y) {
            uchar* e = edges.ptr<uchar>(y);
            const int* l = labels.ptr<int>(y);
            for (int x = 0; x < edges.cols; ++x)
                if (e[x] && drop[l[x]])
                    e[x] = 0;
        }
    }
    return edges;
}

cv::Mat atlasEdges(const cv::Mat& labels) {
    CV_Assert(labels.type() == CV_32S);
    cv::Mat edges = cv::Mat::zeros(labels.size(), CV_8U);
    for (int y = 0; y < labels.rows; ++y) {
        const int* row = labels.ptr<int>(y);
        const int* next = y + 1 < labels.rows ? labels.ptr<int>(y + 1) : nullptr;
        uchar* e = edges.ptr<uchar>(y);
        for (int x = 0; x < labels.cols; ++x) {
            const bool right = x + 1 < labels.cols && row[x + 1] != row[x];
            const bool down = next && next[x] != row[x];
            if (right || down)
                e[x] = 255;
        }
    }
    return edges;
}

} // namespace slicestation::pipeline
