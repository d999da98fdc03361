// OME-TIFF writing and reading: round trips, the OME-XML content, atomic replacement and every
// error path (bad arguments, missing / read-only directory, disk full, unreadable files).
#include "../../common/test_dir.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>

#include <tiffio.h>

#include <fcntl.h>
#include <stdlib.h>
#include <sys/mount.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::test {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;
using daemon::OmeTiffInfo;

/// A tmpfs mounted for one test (root only; tests skip when mounting is not permitted).
class TmpfsMount {
public:
    TmpfsMount(const fs::path& at, unsigned long flags, const std::string& options) : at_(at) {
        fs::create_directories(at_);
        mounted_ = ::mount("tmpfs", at_.c_str(), "tmpfs", flags, options.c_str()) == 0;
    }
    ~TmpfsMount() {
        if (mounted_)
            ::umount2(at_.c_str(), MNT_DETACH);
    }
    bool mounted() const { return mounted_; }

private:
    fs::path at_;
    bool mounted_ = false;
};

std::vector<std::string> listDir(const fs::path& dir) {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(dir))
        names.push_back(e.path().filename().string());
    std::sort(names.begin(), names.end());
    return names;
}

cv::Mat randomImage(int type, int width = 301, int height = 173, std::uint64_t seed = 1) {
    cv::Mat m(height, width, type);
    cv::RNG rng(seed);
    rng.fill(m, cv::RNG::UNIFORM, 0, CV_MAT_DEPTH(type) == CV_16U ? 65536 : 256);
    return m;
}

OmeTiffInfo sampleInfo() {
    OmeTiffInfo info;
    info.umPerPx = 0.65;
    info.stage = {12'345.5, 6'789.25, 2'501.125};
    info.channel = "DAPI & <blue>";
    info.name = "slide 3 \"section\" 05";
    info.exposureUs = 12'500;
    info.gain = 2.5;
    info.acquiredUtc = "2024-05-01T22:13:05.125Z";
    return info;
}

std::string tiffDescription(const fs::path& path) {
    TIFF* tif = TIFFOpen(path.c_str(), "r");
    if (tif == nullptr)
        return {};
    const char* d = nullptr;
    std::string out;
    if (TIFFGetField(tif, TIFFTAG_IMAGEDESCRIPTION, &d) == 1 && d != nullptr)
        out = d;
    TIFFClose(tif);
    return out;
}

/// An 8-bit 4x3 TIFF whose ImageDescription is `description`.
void writeTiffWithDescription(const fs::path& path, const std::string& description) {
    TIFF* tif = TIFFOpen(path.c_str(), "w");
    ASSERT_NE(tif, nullptr);
    TIFFSetField(tif, TIFFTAG_IMAGEWIDTH, 4u);
    TIFFSetField(tif, TIFFTAG_IMAGELENGTH, 3u);
    TIFFSetField(tif, TIFFTAG_SAMPLESPERPIXEL, 1);
    TIFFSetField(tif, TIFFTAG_BITSPERSAMPLE, 8);
    TIFFSetField(tif, TIFFTAG_PHOTOMETRIC, PHOTOMETRIC_MINISBLACK);
    TIFFSetField(tif, TIFFTAG_ROWSPERSTRIP, 3u);
    TIFFSetField(tif, TIFFTAG_IMAGEDESCRIPTION, description.c_str());
    std::array<std::uint8_t, 12> pixels{};
    TIFFWriteEncodedStrip(tif, 0, pixels.data(), 12);
    TIFFClose(tif);
}

std::string runCommand(const std::string& command) {
    std::string out;
    FILE* p = ::popen(command.c_str(), "r");
    if (p == nullptr)
        return out;
    std::array<char, 256> buf{};
    while (std::fgets(buf.data(), buf.size(), p) != nullptr)
        out += buf.data();
    ::pclose(p);
    return out;
}

class OmeTiffRoundTrip : public ::testing::TestWithParam<int> {};

TEST_P(OmeTiffRoundTrip, PixelsAndMetadataComeBackExactly) {
    testing_dir::ScratchDir dir("ome");
    const fs::path file = dir.path() / "s.ome.tif";
    const cv::Mat image = randomImage(GetParam());
    const OmeTiffInfo info = sampleInfo();
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, image, info));
    EXPECT_EQ(listDir(dir.path()), std::vector<std::string>{"s.ome.tif"}); // no .partial left

    auto read = daemon::readOmeTiff(file);
    ASSERT_TRUE(read) << read.error().message;
    ASSERT_EQ(read->image.type(), image.type());
    ASSERT_EQ(read->image.size(), image.size());
    EXPECT_EQ(cv::norm(read->image, image, cv::NORM_INF), 0.0); // lossless, BGR order kept
    const auto& got = read->info;
    EXPECT_EQ(got.umPerPx, info.umPerPx);
    EXPECT_EQ(got.stage.xUm, info.stage.xUm);
    EXPECT_EQ(got.stage.yUm, info.stage.yUm);
    EXPECT_EQ(got.stage.zUm, info.stage.zUm);
    EXPECT_EQ(got.channel, info.channel);
    EXPECT_EQ(got.name, info.name);
    EXPECT_EQ(got.exposureUs, info.exposureUs);
    EXPECT_EQ(got.gain, info.gain);
    EXPECT_EQ(got.acquiredUtc, info.acquiredUtc);

    // Also readable as a plain TIFF (what Fiji's non-OME path sees), deflate-compressed.
    auto plain = core::readImage(file);
    ASSERT_TRUE(plain);
    EXPECT_EQ(cv::norm(*plain, image, cv::NORM_INF), 0.0);
    TIFF* tif = TIFFOpen(file.c_str(), "r");
    ASSERT_NE(tif, nullptr);
    std::uint16_t compression = 0;
    std::uint16_t photometric = 0;
    float xres = 0;
    std::uint16_t resUnit = 0;
    TIFFGetField(tif, TIFFTAG_COMPRESSION, &compression);
    TIFFGetField(tif, TIFFTAG_PHOTOMETRIC, &photometric);
    TIFFGetField(tif, TIFFTAG_XRESOLUTION, &xres);
    TIFFGetField(tif, TIFFTAG_RESOLUTIONUNIT, &resUnit);
    EXPECT_EQ(TIFFNumberOfDirectories(tif), 1);
    TIFFClose(tif);
    EXPECT_EQ(compression, COMPRESSION_ADOBE_DEFLATE);
    EXPECT_EQ(photometric, image.channels() == 3 ? PHOTOMETRIC_RGB : PHOTOMETRIC_MINISBLACK);
    EXPECT_EQ(resUnit, RESUNIT_CENTIMETER);
    EXPECT_NEAR(xres, 1e4 / 0.65, 0.01);
}

INSTANTIATE_TEST_SUITE_P(Types, OmeTiffRoundTrip, ::testing::Values(CV_8UC1, CV_16UC1, CV_8UC3),
                         [](const auto& p) {
                             return p.param == CV_8UC1    ? std::string("Mono8")
                                    : p.param == CV_16UC1 ? std::string("Mono16")
                                                          : std::string("Bgr8");
                         });

TEST(OmeTiff, XmlStatesPixelSizePositionChannelAndDate) {
    testing_dir::ScratchDir dir("ome");
    const fs::path file = dir.path() / "x.ome.tif";
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, randomImage(CV_8UC3, 64, 48), sampleInfo()));
    const std::string xml = tiffDescription(file);
    ASSERT_EQ(xml.rfind("<?xml", 0), 0u) << "OME-XML must open the first IFD's ImageDescription";
    EXPECT_NE(xml.find("xmlns=\"http://www.openmicroscopy.org/Schemas/OME/2016-06\""),
              std::string::npos);

    auto parsed = daemon::parseOmeXml(xml);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->sizeX, 64);
    EXPECT_EQ(parsed->sizeY, 48);
    EXPECT_EQ(parsed->info.umPerPx, 0.65);
    EXPECT_EQ(parsed->info.channel, "DAPI & <blue>");

    // An independent XML parser, when the machine has one (libxml2's xmllint).
    if (runCommand("command -v xmllint").empty()) {
        GTEST_SKIP() << "xmllint not installed: checked with parseOmeXml only";
    }
    const fs::path xmlFile = dir.path() / "ome.xml";
    std::ofstream(xmlFile) << xml;
    const auto xpath = [&](const std::string& expr) {
        std::string out =
            runCommand("xmllint --xpath \"" + expr + "\" '" + xmlFile.string() + "' 2>&1");
        while (!out.empty() && out.back() == '\n')
            out.pop_back();
        return out;
    };
    const std::string pixels = "//*[local-name()='Pixels']";
    const std::string plane = pixels + "/*[local-name()='Plane']";
    EXPECT_EQ(xpath("string(" + pixels + "/@PhysicalSizeX)"), "0.65");
    EXPECT_EQ(xpath("string(" + pixels + "/@PhysicalSizeY)"), "0.65");
    EXPECT_EQ(xpath("string(" + pixels + "/@PhysicalSizeXUnit)"), "µm");
    EXPECT_EQ(xpath("string(" + pixels + "/@Type)"), "uint8");
    EXPECT_EQ(xpath("string(" + pixels + "/@SizeC)"), "3");
    EXPECT_EQ(xpath("string(" + pixels + "/*[local-name()='Channel']/@SamplesPerPixel)"), "3");
    EXPECT_EQ(xpath("string(" + pixels + "/*[local-name()='Channel']/@Name)"), "DAPI & <blue>");
    EXPECT_EQ(xpath("string(" + plane + "/@PositionX)"), "12345.5");
    EXPECT_EQ(xpath("string(" + plane + "/@PositionZ)"), "2501.125");
    EXPECT_EQ(xpath("string(" + plane + "/@PositionYUnit)"), "µm");
    EXPECT_EQ(xpath("string(" + plane + "/@ExposureTimeUnit)"), "µs");
    EXPECT_EQ(xpath("string(//*[local-name()='AcquisitionDate'])"), "2024-05-01T22:13:05.125Z");
    EXPECT_EQ(xpath("string(//*[local-name()='TiffData']/@IFD)"), "0");
    EXPECT_EQ(xpath("string(//*[local-name()='Image']/@Name)"), "slide 3 \"section\" 05");
}

TEST(OmeTiff, EmptyAcquisitionTimeStoresTheTimeOfWriting) {
    testing_dir::ScratchDir dir("ome");
    OmeTiffInfo info = sampleInfo();
    info.acquiredUtc.clear();
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(dir.path() / "t.ome.tif", randomImage(CV_8UC1), info));
    auto read = daemon::readOmeTiff(dir.path() / "t.ome.tif");
    ASSERT_TRUE(read);
    EXPECT_EQ(read->info.acquiredUtc.size(), 20u) << read->info.acquiredUtc; // YYYY-MM-DDThh:mm:ssZ
    EXPECT_EQ(read->info.acquiredUtc.back(), 'Z');
}

TEST(OmeTiff, InvalidArgumentsWriteNothing) {
    testing_dir::ScratchDir dir("ome");
    const fs::path file = dir.path() / "bad.ome.tif";
    const auto expectInvalid = [&](const cv::Mat& image, const OmeTiffInfo& info,
                                   const std::string& why) {
        auto r = daemon::writeOmeTiffAtomic(file, image, info);
        ASSERT_FALSE(r) << why;
        EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument) << why;
        EXPECT_NE(r.error().message.find(file.string()), std::string::npos) << why;
        EXPECT_TRUE(listDir(dir.path()).empty()) << why;
    };
    const OmeTiffInfo good = sampleInfo();
    expectInvalid(cv::Mat(), good, "empty");
    expectInvalid(cv::Mat(4, 4, CV_32FC1, cv::Scalar(0)), good, "float");
    expectInvalid(cv::Mat(4, 4, CV_16UC3, cv::Scalar(0)), good, "16-bit colour");
    expectInvalid(cv::Mat(4, 4, CV_8UC4, cv::Scalar(0)), good, "BGRA");
    for (const double bad : {0.0, -0.5, std::nan("")}) {
        OmeTiffInfo info = good;
        info.umPerPx = bad;
        expectInvalid(randomImage(CV_8UC1), info, "pixel size " + std::to_string(bad));
    }
    OmeTiffInfo info = good;
    info.stage.zUm = INFINITY;
    expectInvalid(randomImage(CV_8UC1), info, "stage");
    info = good;
    info.exposureUs = -1;
    expectInvalid(randomImage(CV_8UC1), info, "exposure");
    info = good;
    info.gain = 0;
    expectInvalid(randomImage(CV_8UC1), info, "gain");
    info = good;
    info.acquiredUtc = "yesterday";
    expectInvalid(randomImage(CV_8UC1), info, "date");
    info = good;
    info.name = "two\nlines";
    expectInvalid(randomImage(CV_8UC1), info, "name");
}

TEST(OmeTiff, MissingDirectoryIsAnIoErrorWithErrno) {
    testing_dir::ScratchDir dir("ome");
    const fs::path file = dir.path() / "no" / "such" / "dir" / "a.ome.tif";
    auto r = daemon::writeOmeTiffAtomic(file, randomImage(CV_8UC1), sampleInfo());
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_EQ(r.error().sysErrno, ENOENT);
    EXPECT_NE(r.error().message.find("a.ome.tif"), std::string::npos) << r.error().message;
    EXPECT_TRUE(listDir(dir.path()).empty());
}

TEST(OmeTiff, ReadOnlyDirectoryLeavesNothing) {
    testing_dir::ScratchDir dir("ome");
    const fs::path ro = dir.path() / "ro";
    std::optional<TmpfsMount> mount;
    if (::geteuid() == 0) {
        // root ignores permission bits: a read-only file system is the honest test.
        mount.emplace(ro, MS_RDONLY, "size=1m");
        if (!mount->mounted())
            GTEST_SKIP() << "running as root without permission to mount";
    } else {
        fs::create_directories(ro);
        fs::permissions(ro, fs::perms::owner_read | fs::perms::owner_exec);
    }
    auto r = daemon::writeOmeTiffAtomic(ro / "a.ome.tif", randomImage(CV_8UC1), sampleInfo());
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_TRUE(r.error().sysErrno == EROFS || r.error().sysErrno == EACCES) << r.error().message;
    EXPECT_TRUE(listDir(ro).empty());
    if (!mount)
        fs::permissions(ro, fs::perms::owner_all);
}

TEST(OmeTiff, DiskFullReportsEnospcAndLeavesNothing) {
    if (::geteuid() != 0)
        GTEST_SKIP() << "needs root to mount a small tmpfs";
    testing_dir::ScratchDir dir("ome");
    const fs::path small = dir.path() / "small";
    TmpfsMount mount(small, 0, "size=64k");
    if (!mount.mounted())
        GTEST_SKIP() << "not permitted to mount a tmpfs";
    // Random 16-bit pixels do not compress: 1 MB of data on a 64 KiB file system.
    auto r = daemon::writeOmeTiffAtomic(small / "big.ome.tif", randomImage(CV_16UC1, 1024, 512, 3),
                                        sampleInfo());
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_EQ(r.error().sysErrno, ENOSPC) << r.error().message;
    EXPECT_NE(r.error().message.find("big.ome.tif"), std::string::npos);
    EXPECT_TRUE(listDir(small).empty());
}

TEST(OmeTiff, AnExistingFileIsNeverReplaced) {
    testing_dir::ScratchDir dir("ome");
    const fs::path file = dir.path() / "r.ome.tif";
    const cv::Mat first = randomImage(CV_16UC1, 200, 100, 1);
    const cv::Mat second = randomImage(CV_16UC1, 120, 80, 2);
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, first, sampleInfo()));
    struct stat oldStat {};
    ASSERT_EQ(::stat(file.c_str(), &oldStat), 0);
    // A stale temporary from a crashed writer (this version's scheme, or an older version's)
    // does not get in the way; the clean-up at start removes it, not the writer.
    std::ofstream(dir.path() / ".r.ome.tif.partial") << "junk from a crash";
    std::ofstream(dir.path() / ".r.ome.tif.tmp.1.2.3") << "junk from a crash";

    OmeTiffInfo info = sampleInfo();
    info.name = "second";
    auto r = daemon::writeOmeTiffAtomic(file, second, info);
    ASSERT_FALSE(r) << "the second image would silently replace the first";
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_EQ(r.error().sysErrno, EEXIST) << r.error().message;
    EXPECT_NE(r.error().message.find("r.ome.tif"), std::string::npos) << r.error().message;
    struct stat still {};
    ASSERT_EQ(::stat(file.c_str(), &still), 0);
    EXPECT_EQ(still.st_ino, oldStat.st_ino);
    auto read = daemon::readOmeTiff(file);
    ASSERT_TRUE(read);
    EXPECT_EQ(cv::norm(read->image, first, cv::NORM_INF), 0.0);
    EXPECT_EQ(listDir(dir.path()),
              (std::vector<std::string>{".r.ome.tif.partial", ".r.ome.tif.tmp.1.2.3", "r.ome.tif"}))
        << "the writer's own temporary is removed";

    // Once the caller has removed the old file (its decision), the new one is written.
    ASSERT_TRUE(fs::remove(file));
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, second, info));
    read = daemon::readOmeTiff(file);
    ASSERT_TRUE(read);
    EXPECT_EQ(read->info.name, "second");
    EXPECT_EQ(cv::norm(read->image, second, cv::NORM_INF), 0.0);
}

TEST(OmeTiff, AFailingWriteReportsItsErrnoAndLeavesNothing) {
    // The injected fault goes through the writer's real error path (no root, no mount).
    testing_dir::ScratchDir dir("ome");
    daemon::setOmeTiffWriteFaultForTesting(ENOSPC);
    auto r =
        daemon::writeOmeTiffAtomic(dir.path() / "full.ome.tif", randomImage(CV_8UC1), sampleInfo());
    daemon::setOmeTiffWriteFaultForTesting(0);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_EQ(r.error().sysErrno, ENOSPC) << r.error().message;
    EXPECT_TRUE(listDir(dir.path()).empty());
    EXPECT_TRUE(daemon::writeOmeTiffAtomic(dir.path() / "full.ome.tif", randomImage(CV_8UC1),
                                           sampleInfo()));
}

TEST(OmeTiff, ReadErrors) {
    testing_dir::ScratchDir dir("ome");
    auto missing = daemon::readOmeTiff(dir.path() / "none.ome.tif");
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);

    std::ofstream(dir.path() / "junk.tif") << "this is not a TIFF at all";
    auto junk = daemon::readOmeTiff(dir.path() / "junk.tif");
    ASSERT_FALSE(junk);
    EXPECT_EQ(junk.error().code, ErrorCode::IoError);

    ASSERT_TRUE(core::writeImage(dir.path() / "plain.tif", randomImage(CV_8UC1, 8, 8)));
    auto plain = daemon::readOmeTiff(dir.path() / "plain.tif");
    ASSERT_FALSE(plain);
    EXPECT_EQ(plain.error().code, ErrorCode::IoError) << "no OME-XML";

    const std::string head = "<?xml version=\"1.0\"?><OME "
                             "xmlns=\"http://www.openmicroscopy.org/Schemas/OME/2016-06\">"
                             "<Image ID=\"Image:0\"><Pixels ID=\"Pixels:0\" Type=\"uint8\" ";
    writeTiffWithDescription(dir.path() / "nosize.tif",
                             head + "SizeX=\"4\" SizeY=\"3\"/></Image></OME>");
    auto noSize = daemon::readOmeTiff(dir.path() / "nosize.tif");
    ASSERT_FALSE(noSize);
    EXPECT_EQ(noSize.error().code, ErrorCode::IoError);
    EXPECT_NE(noSize.error().message.find("PhysicalSizeX"), std::string::npos);

    writeTiffWithDescription(dir.path() / "mismatch.tif",
                             head + "SizeX=\"40\" SizeY=\"3\" PhysicalSizeX=\"1\"/></Image></OME>");
    auto mismatch = daemon::readOmeTiff(dir.path() / "mismatch.tif");
    ASSERT_FALSE(mismatch);
    EXPECT_EQ(mismatch.error().code, ErrorCode::IoError);

    writeTiffWithDescription(dir.path() / "broken.tif", head + "SizeX=\"4\"");
    auto broken = daemon::readOmeTiff(dir.path() / "broken.tif");
    ASSERT_FALSE(broken);
    EXPECT_EQ(broken.error().code, ErrorCode::IoError);

    writeTiffWithDescription(dir.path() / "good.tif",
                             head + "SizeX=\"4\" SizeY=\"3\" PhysicalSizeX=\"2\"/></Image></OME>");
    auto good = daemon::readOmeTiff(dir.path() / "good.tif");
    ASSERT_TRUE(good) << good.error().message;
    EXPECT_EQ(good->info.umPerPx, 2.0);
}

TEST(OmeTiff, UnsupportedPixelTypeOnRead) {
    testing_dir::ScratchDir dir("ome");
    // A float OME-TIFF (another writer's): valid XML, pixel type we do not take.
    const fs::path file = dir.path() / "f.tif";
    TIFF* tif = TIFFOpen(file.c_str(), "w");
    ASSERT_NE(tif, nullptr);
    TIFFSetField(tif, TIFFTAG_IMAGEWIDTH, 2u);
    TIFFSetField(tif, TIFFTAG_IMAGELENGTH, 2u);
    TIFFSetField(tif, TIFFTAG_SAMPLESPERPIXEL, 1);
    TIFFSetField(tif, TIFFTAG_BITSPERSAMPLE, 32);
    TIFFSetField(tif, TIFFTAG_SAMPLEFORMAT, SAMPLEFORMAT_IEEEFP);
    TIFFSetField(tif, TIFFTAG_PHOTOMETRIC, PHOTOMETRIC_MINISBLACK);
    TIFFSetField(tif, TIFFTAG_ROWSPERSTRIP, 2u);
    const std::string xml = daemon::makeOmeXml(2, 2, CV_8UC1, sampleInfo());
    TIFFSetField(tif, TIFFTAG_IMAGEDESCRIPTION, xml.c_str());
    std::array<float, 4> px{};
    TIFFWriteEncodedStrip(tif, 0, px.data(), sizeof(px));
    TIFFClose(tif);
    auto r = daemon::readOmeTiff(file);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Unsupported);
}

TEST(OmeXml, OtherWritersUnitsAreConverted) {
    const std::string xml =
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?><!-- from elsewhere -->"
        "<ome:OME xmlns:ome=\"http://www.openmicroscopy.org/Schemas/OME/2016-06\">"
        "<ome:Image ID=\"Image:0\" Name=\"a&amp;b&#233;\"><ome:Pixels ID=\"Pixels:0\" "
        "SizeX=\"10\" SizeY=\"20\" PhysicalSizeX=\"650\" PhysicalSizeXUnit=\"nm\">"
        "<ome:Channel ID=\"Channel:0:0\" Name=\"GFP\"/>"
        "<ome:Plane TheZ=\"0\" TheC=\"0\" TheT=\"0\" PositionX=\"1.5\" PositionXUnit=\"mm\" "
        "PositionY=\"2e-6\" PositionYUnit=\"m\" PositionZ=\"3\" ExposureTime=\"0.02\"/>"
        "</ome:Pixels></ome:Image></ome:OME>";
    auto r = daemon::parseOmeXml(xml);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_EQ(r->sizeX, 10);
    EXPECT_EQ(r->sizeY, 20);
    EXPECT_NEAR(r->info.umPerPx, 0.65, 1e-12);
    EXPECT_NEAR(r->info.stage.xUm, 1500, 1e-9);
    EXPECT_NEAR(r->info.stage.yUm, 2, 1e-9);
    EXPECT_NEAR(r->info.stage.zUm, 3, 1e-9); // unit absent: the stage's reference frame (µm)
    EXPECT_EQ(r->info.exposureUs, 20'000);   // unit absent: seconds
    EXPECT_EQ(r->info.channel, "GFP");
    EXPECT_EQ(r->info.name, "a&b\xc3\xa9");

    EXPECT_EQ(
        daemon::parseOmeXml("<OME><Image><Pixels SizeX=\"1\" SizeY=\"1\" "
                            "PhysicalSizeX=\"1\" PhysicalSizeXUnit=\"furlong\"/></Image></OME>")
            .error()
            .code,
        ErrorCode::IoError);
    EXPECT_EQ(daemon::parseOmeXml("<OME><Image><Pixels SizeX=\"1\" SizeY=\"1\" "
                                  "PhysicalSizeX=\"-1\"/></Image></OME>")
                  .error()
                  .code,
              ErrorCode::IoError);
    // Found by fuzz_small_formats: a size an int cannot hold was cast anyway (undefined).
    for (const char* size :
         {"16222222222222222222222222222222222222222222222222222222", "-3", "0", "2.5", "nan"}) {
        const auto refused =
            daemon::parseOmeXml(std::string("<OME><Image><Pixels SizeX=\"") + size +
                                "\" SizeY=\"1\" PhysicalSizeX=\"1\"/></Image></OME>");
        ASSERT_FALSE(refused) << size;
        EXPECT_NE(refused.error().message.find("SizeX"), std::string::npos)
            << refused.error().message;
    }
    EXPECT_FALSE(daemon::parseOmeXml("<NotOme/>"));
    EXPECT_FALSE(daemon::parseOmeXml("<OME><Image></OME>"));
}

} // namespace
} // namespace slicestation::test
