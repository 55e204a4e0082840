// rx_adc_top_vectors_main -- the fixed-rate ADC bench under Verilator without --timing:
// toggles rx_adc_top_vectors_check's two clocks from a picosecond time loop
// (cdma_lidar.hdl_ref.adc_top builds and runs it).
//
//   Vrx_adc_top_vectors_check +VEC=<folder>/ +ADC_PS=<ps> +FAB_PS=<ps> [+PHASE_PS=<ps>]
//                             [+GAP_EVERY=<n> +GAP_LEN=<clocks>]
//
// ADC edges at n ADC_PS / 2, fabric edges at PHASE_PS + m FAB_PS / 2 (exact: the loop
// counts half picoseconds); edges that fall together are applied in one evaluation. The
// check module prints the verdict line and calls $finish (its watchdog bounds the run).
// Exit status 2 for a bad argument.
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>

#include "Vrx_adc_top_vectors_check.h"
#include "verilated.h"

static long long plus_arg(int argc, char** argv, const char* name, long long fallback) {
    const std::size_t n = std::strlen(name);
    for (int i = 1; i < argc; ++i)
        if (argv[i][0] == '+' && !std::strncmp(argv[i] + 1, name, n) && argv[i][n + 1] == '=')
            return std::atoll(argv[i] + n + 2);
    return fallback;
}

int main(int argc, char** argv) {
    auto ctx = std::make_unique<VerilatedContext>();
    ctx->commandArgs(argc, argv);
    const long long adc_ps = plus_arg(argc, argv, "ADC_PS", 4000);
    const long long fab_ps = plus_arg(argc, argv, "FAB_PS", 0);
    const long long phase_ps = plus_arg(argc, argv, "PHASE_PS", 0);
    if (adc_ps < 2 || fab_ps < 2 || phase_ps < 0) {
        std::fprintf(stderr, "ADC_PS and FAB_PS must be >= 2 ps, PHASE_PS >= 0\n");
        return 2;
    }
    auto top = std::make_unique<Vrx_adc_top_vectors_check>(ctx.get());
    top->adc_clk = 0;
    top->clk = 0;
    top->eval();
    // in half picoseconds: a half period of P ps is P units
    long long adc_next = adc_ps, fab_next = 2 * phase_ps + fab_ps;
    while (!ctx->gotFinish()) {
        const long long t = adc_next < fab_next ? adc_next : fab_next;
        ctx->time(t / 2);
        if (adc_next == t) { top->adc_clk = !top->adc_clk; adc_next += adc_ps; }
        if (fab_next == t) { top->clk = !top->clk; fab_next += fab_ps; }
        top->eval();
    }
    top->final();
    return 0;
}
