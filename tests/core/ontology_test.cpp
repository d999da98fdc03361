#include "slicestation/core/ontology.hpp"

#include "../common/test_dir.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>

namespace slicestation::core {
namespace {

namespace fs = std::filesystem;

const std::string kHeader =
    "id,atlas_id,name,acronym,parent_structure_id,structure_id_path,color_hex_triplet\n";

class OntologyTest : public testing_dir::TempDirTest {
protected:
    OntologyTest() : TempDirTest("ontology") {}

    fs::path write(const std::string& name, const std::string& text) const {
        const fs::path path = dir_ / name;
        std::ofstream(path, std::ios::binary) << text;
        return path;
    }

    /// Expects InvalidArgument whose message names the file and contains every `mentions`.
    void expectInvalid(const std::string& text, std::initializer_list<std::string> mentions) {
        const fs::path path = write("bad.csv", text);
        const Result<Ontology> ontology = readOntologyCsv(path);
        ASSERT_FALSE(ontology.ok()) << text;
        EXPECT_EQ(ontology.error().code, ErrorCode::InvalidArgument) << ontology.error().message;
        EXPECT_NE(ontology.error().message.find("bad.csv"), std::string::npos)
            << ontology.error().message;
        for (const auto& mention : mentions) {
            EXPECT_NE(ontology.error().message.find(mention), std::string::npos)
                << "'" << ontology.error().message << "' should mention '" << mention << "'";
        }
    }
};

TEST_F(OntologyTest, ParsesQuotingAndBuildsTheTree) {
    const std::string text = "\xEF\xBB\xBF" + kHeader +           // byte-order mark
                             "997,-1,root,root,,/997/,FFFFFF\r\n" // CRLF line end
                             "8,0,\"Basic cell groups, and regions\",grey,997,/997/8/,BFDAE3\n"
                             "\n" // blank line
                             "567,70,\"Cerebrum \"\"CH\"\"\nsecond line\",CH,8,/997/8/567/,b0f0ff\n"
                             "672,83,Caudoputamen,CP,567,/997/8/567/672/,98D6F9\n";
    const Result<Ontology> ontology = readOntologyCsv(write("tree.csv", text));
    ASSERT_TRUE(ontology.ok()) << ontology.error().message;
    ASSERT_EQ(ontology->structures().size(), 4u);

    const Structure* grey = ontology->find(8);
    ASSERT_NE(grey, nullptr);
    EXPECT_EQ(grey->name, "Basic cell groups, and regions");
    EXPECT_EQ(grey->parentId, 997u);
    EXPECT_EQ(grey->colorRgb, 0xBFDAE3u);

    const Structure* cerebrum = ontology->find(567);
    ASSERT_NE(cerebrum, nullptr);
    EXPECT_EQ(cerebrum->name, "Cerebrum \"CH\"\nsecond line");
    EXPECT_EQ(cerebrum->colorRgb, 0xB0F0FFu);

    const Structure* root = ontology->find(997);
    ASSERT_NE(root, nullptr);
    EXPECT_EQ(root->parentId, 0u);
    EXPECT_EQ(root->path, std::vector<std::uint32_t>{997});

    // The record after the quoted line break still parses, on its own line.
    const Structure* cp = ontology->find(672);
    ASSERT_NE(cp, nullptr);
    EXPECT_EQ(cp->acronym, "CP");
    EXPECT_EQ(cp->path, (std::vector<std::uint32_t>{997, 8, 567, 672}));

    EXPECT_EQ(ontology->find(12345), nullptr);
    EXPECT_TRUE(ontology->isDescendantOf(672, 567));
    EXPECT_TRUE(ontology->isDescendantOf(672, 997));
    EXPECT_TRUE(ontology->isDescendantOf(672, 672));
    EXPECT_FALSE(ontology->isDescendantOf(567, 672));
    EXPECT_FALSE(ontology->isDescendantOf(0, 997));
    EXPECT_FALSE(ontology->isDescendantOf(12345, 997));
}

TEST_F(OntologyTest, MissingFileIsNotFound) {
    const Result<Ontology> ontology = readOntologyCsv(dir_ / "absent.csv");
    ASSERT_FALSE(ontology.ok());
    EXPECT_EQ(ontology.error().code, ErrorCode::NotFound);
    EXPECT_NE(ontology.error().message.find("absent.csv"), std::string::npos);
}

TEST_F(OntologyTest, MalformedFilesNameLineAndColumn) {
    expectInvalid("", {"header"});
    expectInvalid("id,name,acronym,parent_structure_id,color_hex_triplet\n1,a,A,,FFFFFF\n",
                  {"line 1", "structure_id_path"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\n8,0,grey,grey,997,/997/8/\n",
                  {"line 3", "expected 7 fields", "got 6"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\nx8,0,grey,grey,997,/997/8/,FFFFFF\n",
                  {"line 3", "column 'id'", "x8"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\n8,0,grey,grey,99x,/997/8/,FFFFFF\n",
                  {"line 3", "column 'parent_structure_id'"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\n8,0,grey,grey,997,/997/9/,FFFFFF\n",
                  {"line 3", "column 'structure_id_path'", "/997/9/"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\n8,0,grey,grey,997,/997/a/8/,FFFFFF\n",
                  {"line 3", "column 'structure_id_path'"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\n8,0,grey,grey,996,/997/8/,FFFFFF\n",
                  {"line 3", "column 'parent_structure_id'", "996"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\n8,0,grey,grey,997,/997/8/,FFFGGG\n",
                  {"line 3", "column 'color_hex_triplet'", "FFFGGG"});
    expectInvalid(kHeader + "997,-1,root,root,,/997/,FFFFFF\n997,0,again,A,,/997/,FFFFFF\n",
                  {"line 3", "already given on line 2"});
    // A quoted field spanning lines: the error reports where the record starts.
    expectInvalid(kHeader + "997,-1,\"root\nstill root\",root,,/997/,FFFFFF\n8,0,g\"rey,g,997,"
                            "/997/8/,FFFFFF\n",
                  {"line 4", "quote"});
    expectInvalid(kHeader + "997,-1,\"root\"x,root,,/997/,FFFFFF\n", {"line 2", "closing quote"});
    expectInvalid(kHeader + "997,-1,\"root,root,,/997/,FFFFFF\n", {"line 2", "never closed"});
}

TEST_F(OntologyTest, CreateRejectsInconsistentStructures) {
    Structure a;
    a.id = 5;
    a.path = {1, 5};
    Structure b = a;
    EXPECT_TRUE(Ontology::create({a}).ok());
    const Result<Ontology> duplicate = Ontology::create({a, b});
    ASSERT_FALSE(duplicate.ok());
    EXPECT_EQ(duplicate.error().code, ErrorCode::InvalidArgument);
    b.id = 6; // path still ends with 5
    EXPECT_FALSE(Ontology::create({a, b}).ok());
    EXPECT_EQ(Ontology().find(5), nullptr);
}

TEST(RealOntology, Allen2017StructureTree) {
    const fs::path path =
        fs::path(SLST_SHARED_DIR) / "atlas/allen-ccf-2017/structure_tree_safe_2017.csv";
    if (!fs::exists(path)) {
        GTEST_SKIP() << "shared data absent: " << path;
    }
    const Result<Ontology> ontology = readOntologyCsv(path);
    ASSERT_TRUE(ontology.ok()) << ontology.error().message;
    EXPECT_EQ(ontology->structures().size(), 1327u);

    const Structure* cp = ontology->find(672);
    ASSERT_NE(cp, nullptr);
    EXPECT_EQ(cp->name, "Caudoputamen");
    EXPECT_EQ(cp->acronym, "CP");
    EXPECT_EQ(cp->parentId, 485u); // Striatum dorsal region
    EXPECT_EQ(cp->colorRgb, 0x98D6F9u);
    EXPECT_EQ(cp->path.front(), 997u);
    EXPECT_EQ(cp->path.back(), 672u);
    EXPECT_NE(std::find(cp->path.begin(), cp->path.end(), 477u), cp->path.end());

    const Structure* striatum = ontology->find(477);
    ASSERT_NE(striatum, nullptr);
    EXPECT_EQ(striatum->name, "Striatum");
    const Structure* root = ontology->find(997);
    ASSERT_NE(root, nullptr);
    EXPECT_EQ(root->name, "root");
    EXPECT_EQ(root->parentId, 0u);

    EXPECT_TRUE(ontology->isDescendantOf(672, 477));
    EXPECT_TRUE(ontology->isDescendantOf(672, 997));
    EXPECT_FALSE(ontology->isDescendantOf(672, 549));       // not in the thalamus
    EXPECT_TRUE(ontology->isDescendantOf(958, 549));        // epithalamus under thalamus (README)
    EXPECT_TRUE(ontology->isDescendantOf(614454277u, 997)); // the largest id is known
    EXPECT_FALSE(ontology->isDescendantOf(997, 672));

    // Every structure's path is made of known ids, root first.
    for (const Structure& s : ontology->structures()) {
        ASSERT_FALSE(s.path.empty());
        EXPECT_EQ(s.path.front(), 997u) << s.id;
        for (std::uint32_t step : s.path) {
            EXPECT_NE(ontology->find(step), nullptr) << "path of " << s.id << " holds " << step;
        }
    }
}

} // namespace
} // namespace slicestation::core
