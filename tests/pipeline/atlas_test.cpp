#include "slicestation/pipeline/atlas.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <set>
#include <vector>

using namespace slicestation;
using namespace slicestation::pipeline;

TEST(LabelsFromImage, AcceptsIdsAndColourCodes) {
    cv::Mat u16 = cv::Mat::zeros(10, 10, CV_16U);
    u16(cv::Rect(2, 2, 5, 5)).setTo(1000);
    auto l = labelsFromImage(u16);
    ASSERT_TRUE(l.ok());
    EXPECT_EQ(l->type(), CV_32S);
    EXPECT_EQ(l->at<int>(3, 3), 1000);

    cv::Mat rgb(10, 10, CV_8UC3, cv::Scalar(255, 255, 255)); // white outside
    rgb(cv::Rect(2, 2, 3, 3)).setTo(cv::Scalar(0, 0, 255));  // BGR red
    rgb(cv::Rect(5, 2, 3, 3)).setTo(cv::Scalar(0, 0, 0));    // black region inside
    auto c = labelsFromImage(rgb);
    ASSERT_TRUE(c.ok());
    EXPECT_EQ(c->at<int>(0, 0), 0);
    EXPECT_EQ(c->at<int>(3, 3), 0xFF0000);
    EXPECT_NE(c->at<int>(3, 6), 0);
    EXPECT_NE(c->at<int>(3, 6), c->at<int>(3, 3));
}

TEST(LabelsFromImage, RejectsInvalidAtlases) {
    EXPECT_FALSE(labelsFromImage(cv::Mat()).ok());
    EXPECT_FALSE(labelsFromImage(cv::Mat::zeros(5, 5, CV_8U)).ok()); // no labels
    EXPECT_FALSE(labelsFromImage(cv::Mat::ones(5, 5, CV_32F)).ok());
    EXPECT_FALSE(labelsFromImage(cv::Mat::ones(5, 5, CV_16UC3)).ok());
}

TEST(CoronalPlane, AllenAndQuickNiiAxes) {
    core::Volume v;
    v.sizes = {4, 3, 5}; // Allen: AP, DV, LR
    v.data.resize(60);
    for (size_t i = 0; i < v.data.size(); ++i)
        v.data[i] = static_cast<std::uint32_t>(i);
    auto p = coronalPlane(v, VolumeAxes::Allen, 2);
    ASSERT_TRUE(p.ok());
    EXPECT_EQ(p->size(), cv::Size(5, 3));
    EXPECT_EQ(static_cast<std::uint32_t>(p->at<int>(1, 4)), v.at(2, 1, 4));
    EXPECT_EQ(coronalPlane(v, VolumeAxes::Allen, 4).error().code, core::ErrorCode::OutOfRange);
    // QuickNII: x = LR (axis 0), y = PA (axis 1), z = IS (axis 2); dorsal (high z) on top.
    auto q = coronalPlane(v, VolumeAxes::QuickNii, 0);
    ASSERT_TRUE(q.ok());
    EXPECT_EQ(q->size(), cv::Size(4, 5));
    EXPECT_EQ(static_cast<std::uint32_t>(q->at<int>(0, 1)), v.at(1, 2, 4));
}

TEST(CollapseLabels, DeepestListedAncestorWins) {
    const auto dir = std::filesystem::temp_directory_path() / "slst_atlas_test";
    std::filesystem::create_directories(dir);
    const auto csv = dir / "tree.csv";
    std::ofstream(csv)
        << "id,name,acronym,parent_structure_id,structure_id_path,color_hex_triplet\n"
           "997,root,root,,/997/,FFFFFF\n"
           "549,Thalamus,TH,997,/997/549/,FF7080\n"
           "958,Epithalamus,EPI,549,/997/549/958/,FF8084\n"
           "10,\"Child, of epi\",CE,958,/997/549/958/10/,FF8084\n"
           "11,Other thal,OT,549,/997/549/11/,FF8084\n"
           "12,Elsewhere,EW,997,/997/12/,FF8084\n";
    auto onto = core::readOntologyCsv(csv);
    ASSERT_TRUE(onto.ok()) << onto.error().message;
    cv::Mat labels = (cv::Mat_<int>(1, 5) << 0, 10, 11, 12, 99999);
    const cv::Mat c = collapseLabels(labels, *onto, {549, 958}, 7);
    EXPECT_EQ(c.at<int>(0, 0), 0);
    EXPECT_EQ(c.at<int>(0, 1), 958);
    EXPECT_EQ(c.at<int>(0, 2), 549);
    EXPECT_EQ(c.at<int>(0, 3), 7);
    EXPECT_EQ(c.at<int>(0, 4), 7); // unknown id

    // The ids a plane shows (0 left out, each once) and those under an ancestor, itself
    // included; unknown ids lie under nothing.
    std::set<std::int32_t> ids;
    collectIds(labels, ids);
    collectIds((cv::Mat_<int>(1, 3) << 958, 10, 0), ids);
    EXPECT_EQ(ids, (std::set<std::int32_t>{10, 11, 12, 958, 99999}));
    EXPECT_EQ(idsUnder(ids, *onto, 958), (std::vector<std::int32_t>{10, 958}));
    EXPECT_EQ(idsUnder(ids, *onto, 549), (std::vector<std::int32_t>{10, 11, 958}));
    EXPECT_TRUE(idsUnder(ids, *onto, 4242).empty());
    std::filesystem::remove_all(dir);
}
