// The record files of the CPU drivers (emulate_main.cpp here and in crates/nn/cuda), little-endian, until end of
// file: u32 name_len, name bytes, u32 dtype (0 = f32, 1 = i32, 2 = u32), u64 count, count * 4 bytes.
#pragma once

#include <cstdint>
#include <cstring>
#include <fstream>
#include <map>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

namespace records {

struct Rec {
    uint32_t dtype = 0;
    std::vector<uint32_t> raw;  // 4-byte words
};

std::map<std::string, Rec> read_records(const char* path) {
    std::ifstream f(path, std::ios::binary);
    if (!f) throw std::runtime_error(std::string("cannot open ") + path);
    std::map<std::string, Rec> out;
    for (;;) {
        uint32_t len;
        if (!f.read(reinterpret_cast<char*>(&len), 4)) break;
        std::string name(len, '\0');
        Rec r;
        uint64_t count;
        f.read(name.data(), len);
        f.read(reinterpret_cast<char*>(&r.dtype), 4);
        f.read(reinterpret_cast<char*>(&count), 8);
        r.raw.resize(count);
        f.read(reinterpret_cast<char*>(r.raw.data()), 4 * count);
        if (!f) throw std::runtime_error("truncated record " + name);
        out[name] = std::move(r);
    }
    return out;
}

template <class T>
std::vector<T> take(const std::map<std::string, Rec>& m, const std::string& name, size_t want) {
    auto it = m.find(name);
    if (it == m.end()) throw std::runtime_error("missing input " + name);
    if (it->second.raw.size() != want)
        throw std::runtime_error("input " + name + ": expected " + std::to_string(want) + " values, got " +
                                 std::to_string(it->second.raw.size()));
    std::vector<T> v(want);
    std::memcpy(v.data(), it->second.raw.data(), 4 * want);
    return v;
}

struct Writer {
    std::ofstream f;
    explicit Writer(const char* path) : f(path, std::ios::binary) {
        if (!f) throw std::runtime_error(std::string("cannot create ") + path);
    }
    template <class T>
    void put(const std::string& name, const std::vector<T>& v) {
        static_assert(sizeof(T) == 4);
        const uint32_t len = name.size();
        const uint32_t dtype = std::is_same_v<T, float> ? 0 : std::is_same_v<T, int> ? 1 : 2;
        const uint64_t count = v.size();
        f.write(reinterpret_cast<const char*>(&len), 4);
        f.write(name.data(), len);
        f.write(reinterpret_cast<const char*>(&dtype), 4);
        f.write(reinterpret_cast<const char*>(&count), 8);
        f.write(reinterpret_cast<const char*>(v.data()), 4 * count);
    }
};

}  // namespace records
