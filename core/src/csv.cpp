#include "slicestation/core/csv.hpp"

namespace slicestation::core {
namespace {

/// Reads the records of one CSV text; `i_` walks it, `line_` counts physical lines.
class CsvParser {
public:
    CsvParser(std::string_view text, const std::string& where) : text_(text), where_(where) {
        if (text_.substr(0, 3) == "\xEF\xBB\xBF")
            i_ = 3; // UTF-8 byte-order mark
    }

    Result<std::vector<CsvRecord>> records() {
        std::vector<CsvRecord> out;
        while (i_ < text_.size()) {
            CsvRecord record;
            record.line = line_;
            for (;;) {
                auto field = nextField(static_cast<int>(record.fields.size()) + 1);
                if (!field)
                    return field.error();
                record.fields.push_back(std::move(*field));
                if (at(',')) {
                    ++i_;
                    continue;
                }
                if (at('\r'))
                    ++i_;
                if (at('\n')) {
                    ++i_;
                    ++line_;
                }
                break;
            }
            if (record.fields.size() == 1 && record.fields.front().empty())
                continue; // blank line
            out.push_back(std::move(record));
        }
        return out;
    }

private:
    bool at(char c) const { return i_ < text_.size() && text_[i_] == c; }
    bool atFieldEnd() const { return i_ >= text_.size() || at(',') || at('\r') || at('\n'); }

    Error fail(int line, int field, const char* what) const {
        return makeError(ErrorCode::InvalidArgument, where_ + ": line " + std::to_string(line) +
                                                         ", field " + std::to_string(field) + ": " +
                                                         what);
    }

    Result<std::string> nextField(int fieldNumber) {
        std::string field;
        if (!at('"')) {
            while (!atFieldEnd()) {
                if (at('"'))
                    return fail(line_, fieldNumber, "quote inside an unquoted field");
                field += text_[i_++];
            }
            return field;
        }
        const int quoteLine = line_;
        ++i_;
        for (;;) {
            if (i_ >= text_.size())
                return fail(quoteLine, fieldNumber, "quoted field is never closed");
            if (at('"')) {
                if (i_ + 1 < text_.size() && text_[i_ + 1] == '"') {
                    field += '"';
                    i_ += 2;
                    continue;
                }
                ++i_;
                break;
            }
            if (at('\n'))
                ++line_;
            field += text_[i_++];
        }
        if (!atFieldEnd())
            return fail(line_, fieldNumber, "unexpected character after closing quote");
        return field;
    }

    std::string_view text_;
    const std::string& where_;
    std::size_t i_ = 0;
    int line_ = 1;
};

} // namespace

Result<std::vector<CsvRecord>> parseCsv(std::string_view text, const std::string& where) {
    return CsvParser(text, where).records();
}

} // namespace slicestation::core
