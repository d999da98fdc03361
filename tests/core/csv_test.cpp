// The one CSV reader: RFC 4180 quoting, line ends, byte-order mark, and errors naming the line.
#include "slicestation/core/csv.hpp"

#include <gtest/gtest.h>

using namespace slicestation;
using core::parseCsv;

namespace {

std::vector<std::vector<std::string>> fieldsOf(const std::vector<core::CsvRecord>& records) {
    std::vector<std::vector<std::string>> out;
    for (const auto& r : records)
        out.push_back(r.fields);
    return out;
}

TEST(Csv, QuotedFieldsHoldCommasQuotesAndLineBreaks) {
    auto r = parseCsv("a,\"b,c\",\"say \"\"hi\"\"\"\n\"two\nlines\",,x\n", "t.csv");
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_EQ(fieldsOf(*r), (std::vector<std::vector<std::string>>{{"a", "b,c", "say \"hi\""},
                                                                   {"two\nlines", "", "x"}}));
    EXPECT_EQ((*r)[0].line, 1);
    EXPECT_EQ((*r)[1].line, 2);
}

TEST(Csv, CrlfBomBlankLinesAndNoFinalNewline) {
    auto r = parseCsv("\xEF\xBB\xBFid,name\r\n\r\n1,root\r\n\n2, spaced \r\n3,last", "t.csv");
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_EQ(fieldsOf(*r), (std::vector<std::vector<std::string>>{
                                {"id", "name"}, {"1", "root"}, {"2", " spaced "}, {"3", "last"}}));
    EXPECT_EQ((*r)[1].line, 3) << "blank lines still count";
    EXPECT_EQ((*r)[3].line, 6);
    EXPECT_TRUE(parseCsv("", "t.csv")->empty());
    EXPECT_TRUE(parseCsv("\xEF\xBB\xBF", "t.csv")->empty());
}

TEST(Csv, LineNumbersCountLineBreaksInsideQuotes) {
    auto r = parseCsv("a\n\"x\ny\"\nb\n", "t.csv");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->size(), 3u);
    EXPECT_EQ((*r)[2].line, 4);
}

TEST(Csv, BrokenQuotingIsAnErrorNamingLineAndField) {
    struct Case {
        const char* text;
        const char* message;
    };
    for (const Case& c : {
             Case{"a,b\nc,\"open\n\n", "t.csv: line 2, field 2: quoted field is never closed"},
             Case{"a\n\nb\"c\n", "t.csv: line 3, field 1: quote inside an unquoted field"},
             Case{"\"a\"b,c\n", "t.csv: line 1, field 1: unexpected character after closing quote"},
             Case{"x,\"multi\nline\"z\n", "t.csv: line 2, field 2: unexpected character after"},
         }) {
        auto r = parseCsv(c.text, "t.csv");
        ASSERT_FALSE(r) << c.text;
        EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument);
        EXPECT_EQ(r.error().message.rfind(c.message, 0), 0u) << r.error().message;
    }
}

} // namespace
