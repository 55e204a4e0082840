// rx_top_engine -- drives the Verilator model of rx_top from a text job on stdin and
// prints every output word on stdout (cdma_lidar.hdl_ref.engine builds and runs it).
//
// stdin:  <n_ports>, then per configuration port: <name> <n_words> <word>... (32-bit
//         hex words, least significant first); then <columns> <samples per column>
//         <samples per clock> <ADC_W> <max clocks>; then every sample (decimal, column
//         by column).
// stdout: "C <channel> <index> <hex word>" per corr_valid clock, "R <channel> <hex>..."
//         per res_valid clock (the result ports in RESULT_PORTS order, each one hex
//         number), then "DONE <clocks>".
// Exit status 3 when done has not come after <max clocks> clocks (a hang), 2 for a bad job.
#include <cstdint>
#include <cstdio>
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include "Vrx_top.h"
#include "verilated.h"

using Words = std::vector<uint32_t>;

template <class T> static void setp(T& port, const Words& w) {
    uint64_t v = w.empty() ? 0 : w[0];
    if (w.size() > 1) v |= static_cast<uint64_t>(w[1]) << 32;
    port = static_cast<T>(v);
}
template <std::size_t N> static void setp(VlWide<N>& port, const Words& w) {
    for (std::size_t i = 0; i < N; ++i) port[i] = i < w.size() ? w[i] : 0;
}
template <class T> static std::string hexp(const T& port) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%llx", static_cast<unsigned long long>(port));
    return buf;
}
template <std::size_t N> static std::string hexp(const VlWide<N>& port) {
    std::string s;
    char buf[16];
    for (std::size_t i = N; i-- > 0;) {
        std::snprintf(buf, sizeof buf, s.empty() ? "%x" : "%08x", port[i]);
        s += buf;
    }
    return s;
}

#define CFG_PORTS X(cfg_columns) X(cfg_degree) X(cfg_taps_u) X(cfg_taps_v) X(cfg_seed_u) \
    X(cfg_seed_v) X(cfg_spc) X(cfg_averages) X(cfg_uid_bits) X(cfg_uid) X(cfg_gate_start) \
    X(cfg_gate_len) X(cfg_peak_exclude) X(cfg_ghost_start) X(cfg_ghost_len) X(cfg_out_shift) \
    X(cfg_rounding) X(cfg_out_bits) X(cfg_peaks)
#define RESULT_PORTS X(res_found) X(res_lag) X(res_index) X(res_peak) X(res_neg) X(res_nz) \
    X(res_nb_lo) X(res_nb_hi) X(res_noise_count) X(res_noise_sum) X(res_noise_sumsq) \
    X(res_uid_observed) X(res_uid_match) X(res_saturated)

int main(int argc, char** argv) {
    auto ctx = std::make_unique<VerilatedContext>();
    ctx->commandArgs(argc, argv);
    auto top = std::make_unique<Vrx_top>(ctx.get());
    std::ios::sync_with_stdio(false);
    int n_ports = 0;
    if (!(std::cin >> n_ports)) return 2;
    for (int i = 0; i < n_ports; ++i) {
        std::string name;
        int n = 0;
        std::cin >> name >> n;
        Words w(n);
        for (auto& x : w) std::cin >> std::hex >> x >> std::dec;
        bool known = false;
#define X(p) if (name == #p) { setp(top->p, w); known = true; }
        CFG_PORTS
#undef X
        if (!known) { std::cerr << "unknown port " << name << "\n"; return 2; }
    }
    long long columns = 0, per_col = 0, p_in = 1, adc_w = 1, max_clocks = 0;
    std::cin >> columns >> per_col >> p_in >> adc_w >> max_clocks;
    const long long total = columns * per_col;
    std::vector<int64_t> samples(total);
    for (auto& x : samples) std::cin >> x;
    if (!std::cin) { std::cerr << "short job\n"; return 2; }
    if (adc_w < 1 || adc_w > 32) { std::cerr << "ADC_W must be 1..32\n"; return 2; }
    const uint64_t mask = (1ULL << adc_w) - 1;

    auto edge = [&]() { top->clk = 1; top->eval(); top->clk = 0; top->eval(); };
    top->clk = 0; top->rst = 1; top->start = 0; top->stop = 0; top->clear_err = 0;
    top->s_valid = 0; top->eval();
    edge(); edge();
    top->rst = 0; edge();
    top->start = 1; edge(); top->start = 0;
    long long taken = 0, clocks = 0;
    std::string out;
    out.reserve(1 << 20);
    for (;;) {
        const bool valid = taken < total;
        top->s_valid = valid;
        Words word((p_in * adc_w + 31) / 32, 0);
        for (long long k = 0; valid && k < p_in; ++k) {
            const uint64_t x = static_cast<uint64_t>(samples[taken + k]) & mask;
            const long long bit = k * adc_w;
            word[bit / 32] |= static_cast<uint32_t>(x << (bit % 32));
            if (bit % 32 + adc_w > 32) word[bit / 32 + 1] |= static_cast<uint32_t>(x >> (32 - bit % 32));
        }
        setp(top->s_data, word);
        top->eval();
        const bool take = valid && top->s_ready;
        if (top->corr_valid)
            out += "C " + std::to_string(top->corr_channel) + " " +
                   std::to_string(top->corr_index) + " " + hexp(top->corr_data) + "\n";
        if (top->res_valid) {
            out += "R " + std::to_string(top->res_channel);
#define X(p) out += " " + hexp(top->p);
            RESULT_PORTS
#undef X
            out += "\n";
        }
        if (top->done) break;
        edge();
        if (take) taken += p_in;
        if (++clocks > max_clocks) {
            std::fputs(out.c_str(), stdout);
            std::cerr << "rx_top: no done after " << max_clocks << " clocks\n";
            return 3;
        }
    }
    out += "DONE " + std::to_string(clocks) + "\n";
    std::fputs(out.c_str(), stdout);
    top->final();
    return 0;
}
