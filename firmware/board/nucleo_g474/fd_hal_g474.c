/* fluxdrive board port for the NUCLEO-G474RE power-stage set (see fd_board.h): clock tree,
 * peripherals, the fd_hal.h calls on registers, and the interrupt handlers. Register names
 * come from g474_regs.h (generated from the stm32g4 crate); the Cortex-M core registers
 * (NVIC, SCB) are the ARMv7-M architecture's. RM0440 is the reference manual. */
#include <stddef.h>

#include "fd_board.h"
#include "fd_can.h"
#include "fd_can_words.h"
#include "fd_hal.h"
#include "g474_regs.h"

fd_board_t fd_board;
fd_core_t fd_board_core;

/* where a debugger (and the virtual board) finds the drive state in RAM: sizeof and the
 * offsets of fd_core_t's fields it reads, then sizeof(fd_board_t) */
const uint32_t fd_board_debug[] = {
    (uint32_t)sizeof(fd_core_t),
    (uint32_t)offsetof(fd_core_t, k),
    (uint32_t)offsetof(fd_core_t, armed),
    (uint32_t)offsetof(fd_core_t, pwm_enabled),
    (uint32_t)offsetof(fd_core_t, fault_latched),
    (uint32_t)offsetof(fd_core_t, split),
    (uint32_t)offsetof(fd_core_t, fault_code),
    (uint32_t)offsetof(fd_core_t, mode),
    (uint32_t)offsetof(fd_core_t, stats),
    (uint32_t)offsetof(fd_core_t, prm),
    (uint32_t)offsetof(fd_core_t, ref_box),
    (uint32_t)offsetof(fd_core_t, cmds),
    (uint32_t)sizeof(fd_duty_cmd_t),
    (uint32_t)FD_CMD_SLOTS,
    (uint32_t)offsetof(fd_core_t, ref_box_taken),
    (uint32_t)offsetof(fd_core_t, cmd_ring),
    (uint32_t)FD_CMD_RING,
    (uint32_t)sizeof(fd_board_t),
    (uint32_t)offsetof(fd_core_t, next_status_k), /* what the lockstep bench restarts */
    (uint32_t)offsetof(fd_core_t, next_fault_k),
    (uint32_t)offsetof(fd_core_t, last_cmd_k),
    (uint32_t)offsetof(fd_core_t, last_ref_k),
    (uint32_t)offsetof(fd_core_t, ran_first),
};

/* ---- Cortex-M4 core registers (ARMv7-M architecture reference) */
#define NVIC_ISER(n) G4_REG(0xE000E100u + 4u * (n))
#define NVIC_IPR_BYTE(n) (*(volatile uint8_t *)(uintptr_t)(0xE000E400u + (n)))

static void nvic_enable(uint32_t irq, uint8_t priority)
{
    NVIC_IPR_BYTE(irq) = (uint8_t)(priority << 4); /* 4 priority bits on the G4 */
    NVIC_ISER(irq >> 5) = 1u << (irq & 31u);
}

#define FIELD(reg, f, v) (((uint32_t)(v) << reg##_##f##_Pos) & reg##_##f##_Msk)

/* ------------------------------------------------------------------ clock tree */

/* HSE 24 MHz (HSI16 if the crystal does not start) -> PLL /M -> 4 MHz x85 = 340 MHz VCO,
 * /2 = 170 MHz SYSCLK (range 1 boost); flash 4 wait states with prefetch and caches;
 * AHB /2 for the switch-over (RM0440 6.1.5: no step above 80 MHz at once), then /1. */
void fd_board_clock_init(void)
{
    G4_RCC_APB1ENR1 |= G4_RCC_APB1ENR1_PWREN_Msk;
    (void)G4_RCC_APB1ENR1;
    G4_PWR_CR5 &= ~G4_PWR_CR5_R1MODE_Msk; /* range 1 boost: up to 170 MHz */
    G4_FLASH_ACR = FIELD(G4_FLASH_ACR, LATENCY, 4u) | G4_FLASH_ACR_PRFTEN_Msk |
                   G4_FLASH_ACR_ICEN_Msk | G4_FLASH_ACR_DCEN_Msk;
    while ((G4_FLASH_ACR & G4_FLASH_ACR_LATENCY_Msk) != FIELD(G4_FLASH_ACR, LATENCY, 4u)) {
    }
    uint32_t pllm = 6u; /* 24 MHz / 6 = 4 MHz */
    uint32_t src = 3u;  /* PLLSRC: HSE */
    G4_RCC_CR |= G4_RCC_CR_HSEON_Msk;
    uint32_t n = 0;
    while (!(G4_RCC_CR & G4_RCC_CR_HSERDY_Msk) && n < 100000u) {
        ++n;
    }
    fd_board.clock_source = 1u;
    if (!(G4_RCC_CR & G4_RCC_CR_HSERDY_Msk)) {
        G4_RCC_CR &= ~G4_RCC_CR_HSEON_Msk;
        G4_RCC_CR |= G4_RCC_CR_HSION_Msk;
        while (!(G4_RCC_CR & G4_RCC_CR_HSIRDY_Msk)) {
        }
        pllm = 4u; /* 16 MHz / 4 = 4 MHz */
        src = 2u;  /* PLLSRC: HSI16 */
        fd_board.clock_source = 2u;
    }
    G4_RCC_CR &= ~G4_RCC_CR_PLLON_Msk;
    while (G4_RCC_CR & G4_RCC_CR_PLLRDY_Msk) {
    }
    G4_RCC_PLLCFGR = FIELD(G4_RCC_PLLCFGR, PLLSRC, src) | FIELD(G4_RCC_PLLCFGR, PLLM, pllm - 1u) |
                     FIELD(G4_RCC_PLLCFGR, PLLN, 85u) | FIELD(G4_RCC_PLLCFGR, PLLR, 0u) |
                     G4_RCC_PLLCFGR_PLLREN_Msk | FIELD(G4_RCC_PLLCFGR, PLLQ, 0u) |
                     G4_RCC_PLLCFGR_PLLQEN_Msk;
    G4_RCC_CR |= G4_RCC_CR_PLLON_Msk;
    while (!(G4_RCC_CR & G4_RCC_CR_PLLRDY_Msk)) {
    }
    G4_RCC_CFGR = (G4_RCC_CFGR & ~(G4_RCC_CFGR_HPRE_Msk | G4_RCC_CFGR_SW_Msk)) |
                  FIELD(G4_RCC_CFGR, HPRE, 8u) | FIELD(G4_RCC_CFGR, SW, 3u); /* AHB /2, PLL */
    while ((G4_RCC_CFGR & G4_RCC_CFGR_SWS_Msk) != FIELD(G4_RCC_CFGR, SWS, 3u)) {
    }
    for (volatile uint32_t i = 0; i < 200u; ++i) { /* >= 1 us at 85 MHz */
    }
    G4_RCC_CFGR &= ~G4_RCC_CFGR_HPRE_Msk; /* AHB /1: 170 MHz; APB1/APB2 /1 */
}

/* ------------------------------------------------------------------ pins */

#define FD_PIN_EN 11u     /* PC11: STDRIVE101 EN */
#define FD_PIN_NFAULT 10u /* PC10: STDRIVE101 nFAULT (open drain, low = fault) */

static void pin_mode(volatile uint32_t *moder, uint32_t pin, uint32_t mode)
{
    *moder = (*moder & ~(3u << (2u * pin))) | (mode << (2u * pin));
}

static void pin_af(volatile uint32_t *afrl, volatile uint32_t *afrh, uint32_t pin, uint32_t af)
{
    volatile uint32_t *r = pin < 8u ? afrl : afrh;
    uint32_t s = 4u * (pin & 7u);
    *r = (*r & ~(0xFu << s)) | (af << s);
}

#define GPIO(P) &G4_GPIO##P##_MODER, &G4_GPIO##P##_AFRL, &G4_GPIO##P##_AFRH
static void af_pin(volatile uint32_t *moder, volatile uint32_t *afrl, volatile uint32_t *afrh,
                   uint32_t pin, uint32_t af)
{
    pin_af(afrl, afrh, pin, af);
    pin_mode(moder, pin, 2u);
}

static void pins_init(void)
{
    G4_RCC_AHB2ENR |= G4_RCC_AHB2ENR_GPIOAEN_Msk | G4_RCC_AHB2ENR_GPIOBEN_Msk |
                      G4_RCC_AHB2ENR_GPIOCEN_Msk;
    (void)G4_RCC_AHB2ENR;
    /* gate driver EN (PC11, low = disabled) before anything switches; nFAULT (PC10) */
    G4_GPIOC_BSRR = 1u << (FD_PIN_EN + 16u);
    pin_mode(&G4_GPIOC_MODER, FD_PIN_EN, 1u);
    pin_mode(&G4_GPIOC_MODER, FD_PIN_NFAULT, 0u);
    G4_GPIOC_PUPDR = (G4_GPIOC_PUPDR & ~(3u << (2u * FD_PIN_NFAULT))) |
                     (1u << (2u * FD_PIN_NFAULT)); /* open-drain nFAULT: pull-up */
    /* TIM1 CH1..3 PA8/PA9/PA10, CH1N..3N PA7/PB0/PB1 (AF6) */
    af_pin(GPIO(A), 8u, 6u);
    af_pin(GPIO(A), 9u, 6u);
    af_pin(GPIO(A), 10u, 6u);
    af_pin(GPIO(A), 7u, 6u);
    af_pin(GPIO(B), 0u, 6u);
    af_pin(GPIO(B), 1u, 6u);
    /* analog: I_a PA0, I_bus PA1 (COMP1+), I_c PC0, I_b PC1, NTC PC2, V_bus PC3 */
    pin_mode(&G4_GPIOA_MODER, 0u, 3u);
    pin_mode(&G4_GPIOA_MODER, 1u, 3u);
    for (uint32_t p = 0; p < 4u; ++p) {
        pin_mode(&G4_GPIOC_MODER, p, 3u);
    }
    /* FDCAN1 RX PB8, TX PB9 (AF9) */
    af_pin(GPIO(B), 8u, 9u);
    af_pin(GPIO(B), 9u, 9u);
    /* encoder TIM4 CH1/CH2 PB6/PB7 (AF2) */
    af_pin(GPIO(B), 6u, 2u);
    af_pin(GPIO(B), 7u, 2u);
    /* line-voltage comparators (add-on board): v_ab +/- TIM3 CH1 PB4 / CH4 PC9 (AF2),
     * v_bc +/- TIM5 CH1 PB2 / CH3 PA2 (AF2), v_ca +/- TIM8 CH1 PC6 / CH3 PC8 (AF4) */
    af_pin(GPIO(B), 4u, 2u);
    af_pin(GPIO(C), 9u, 2u);
    af_pin(GPIO(B), 2u, 2u);
    af_pin(GPIO(A), 2u, 2u);
    af_pin(GPIO(C), 6u, 4u);
    af_pin(GPIO(C), 8u, 4u);
}

/* ------------------------------------------------------------------ TIM1 PWM */

static uint32_t deadtime_dtg(uint32_t ns)
{
    /* RM0440 TIMx_BDTR.DTG with tDTS = 1/170 MHz (5.88 ns): DTG[7:5] = 0xx: DT = DTG[6:0] x
     * tDTS (up to 747 ns); 10x: (64 + DTG[5:0]) x 2 tDTS (up to 1.5 us); 110: (32 +
     * DTG[4:0]) x 8 tDTS (up to 3 us) */
    uint32_t ticks = (ns * 17u + 99u) / 100u; /* ceil(ns * 0.17) */
    if (ticks <= 127u) {
        return ticks;
    }
    if (ticks <= 2u * 127u) {
        uint32_t d = (ticks + 1u) / 2u;
        return 0x80u | (d > 64u ? d - 64u : 0u);
    }
    uint32_t d = (ticks + 7u) / 8u;
    return 0xC0u | (d > 32u ? (d - 32u > 31u ? 31u : d - 32u) : 0u);
}

static void tim1_init(void)
{
    G4_RCC_APB2ENR |= G4_RCC_APB2ENR_TIM1EN_Msk;
    (void)G4_RCC_APB2ENR;
    G4_TIM1_CR1 = FIELD(G4_TIM1_CR1, CMS, 1u) | G4_TIM1_CR1_ARPE_Msk; /* centre-aligned 1 */
    G4_TIM1_PSC = 0u;
    G4_TIM1_ARR = FD_BOARD_TIM1_ARR;
    G4_TIM1_RCR = 1u; /* one update per period: at the valley */
    /* PWM mode 2 (active while CNT > CCR: high sides on around the peak, low sides and
     * the shunts conducting around the valley where the ADC samples), preload on */
    uint32_t pwm2 = 7u;
    G4_TIM1_CCMR1_OUTPUT = FIELD(G4_TIM1_CCMR1_OUTPUT, OC1M, pwm2) |
                           G4_TIM1_CCMR1_OUTPUT_OC1PE_Msk |
                           FIELD(G4_TIM1_CCMR1_OUTPUT, OC2M, pwm2) |
                           G4_TIM1_CCMR1_OUTPUT_OC2PE_Msk;
    G4_TIM1_CCMR2_OUTPUT = FIELD(G4_TIM1_CCMR2_OUTPUT, OC3M, pwm2) |
                           G4_TIM1_CCMR2_OUTPUT_OC3PE_Msk;
    G4_TIM1_CCR1 = FD_BOARD_TIM1_ARR; /* duty 0 */
    G4_TIM1_CCR2 = FD_BOARD_TIM1_ARR;
    G4_TIM1_CCR3 = FD_BOARD_TIM1_ARR;
    G4_TIM1_CCER = G4_TIM1_CCER_CC1E_Msk | G4_TIM1_CCER_CC1NE_Msk | G4_TIM1_CCER_CC2E_Msk |
                   G4_TIM1_CCER_CC2NE_Msk | G4_TIM1_CCER_CC3E_Msk | G4_TIM1_CCER_CC3NE_Msk;
    /* TRGO on update (ADC injected trigger, capture timer reset) */
    G4_TIM1_CR2 = FIELD(G4_TIM1_CR2, MMS, 2u);
    /* break: COMP1 (hardware over-current), active high, no automatic re-enable; off
     * state: outputs at their idle level (all switches off) */
    G4_TIM1_AF1 = G4_TIM1_AF1_BKCMP1E_Msk;
    G4_TIM1_BDTR = FIELD(G4_TIM1_BDTR, DTG, deadtime_dtg(FD_BOARD_DEADTIME_NS)) |
                   G4_TIM1_BDTR_OSSI_Msk | G4_TIM1_BDTR_OSSR_Msk | G4_TIM1_BDTR_BKE_Msk |
                   G4_TIM1_BDTR_BKP_Msk;
    G4_TIM1_DIER = G4_TIM1_DIER_BIE_Msk;
    G4_TIM1_EGR = G4_TIM1_EGR_UG_Msk; /* load ARR, RCR, compare shadows */
    G4_TIM1_SR = 0u;
    G4_TIM1_CR1 |= G4_TIM1_CR1_CEN_Msk;
}

/* ------------------------------------------------------------------ ADC */

static void adc_enable(volatile uint32_t *cr, volatile uint32_t *isr)
{
    *cr &= ~G4_ADC1_CR_DEEPPWD_Msk;
    *cr |= G4_ADC1_CR_ADVREGEN_Msk;
    for (volatile uint32_t i = 0; i < 4000u; ++i) { /* tADCVREG_STUP 20 us */
    }
    *cr |= G4_ADC1_CR_ADCAL_Msk; /* single-ended calibration */
    while (*cr & G4_ADC1_CR_ADCAL_Msk) {
    }
    *isr = G4_ADC1_ISR_ADRDY_Msk;
    *cr |= G4_ADC1_CR_ADEN_Msk;
    while (!(*isr & G4_ADC1_ISR_ADRDY_Msk)) {
    }
}

static void adc_init(void)
{
    G4_RCC_CCIPR = (G4_RCC_CCIPR & ~G4_RCC_CCIPR_ADC12SEL_Msk) | FIELD(G4_RCC_CCIPR, ADC12SEL, 2u);
    G4_RCC_AHB2ENR |= G4_RCC_AHB2ENR_ADC12EN_Msk;
    (void)G4_RCC_AHB2ENR;
    G4_ADC12_COMMON_CCR = FIELD(G4_ADC12_COMMON_CCR, PRESC, 2u); /* SYSCLK / 4 = 42.5 MHz */
    adc_enable(&G4_ADC1_CR, &G4_ADC1_ISR);
    adc_enable(&G4_ADC2_CR, &G4_ADC2_ISR);
    /* 12 bit, right aligned; 6.5 cycles per sample on the current channels */
    G4_ADC1_SMPR1 = 0x00249249u & 0x3FFFFFFFu; /* 001 (6.5 cycles) for IN0..IN9 */
    G4_ADC2_SMPR1 = 0x00249249u & 0x3FFFFFFFu;
    /* ADC1 injected: I_a (IN1), I_b (IN7), I_c (IN6), V_bus (IN9); ADC2 injected: NTC (IN8);
     * both on TIM1 TRGO (JEXTSEL 0), rising edge */
    G4_ADC1_JSQR = FIELD(G4_ADC1_JSQR, JL, 3u) | FIELD(G4_ADC1_JSQR, JEXTSEL, 0u) |
                   FIELD(G4_ADC1_JSQR, JEXTEN, 1u) | FIELD(G4_ADC1_JSQR, JSQ1, 1u) |
                   FIELD(G4_ADC1_JSQR, JSQ2, 7u) | FIELD(G4_ADC1_JSQR, JSQ3, 6u) |
                   FIELD(G4_ADC1_JSQR, JSQ4, 9u);
    G4_ADC2_JSQR = FIELD(G4_ADC2_JSQR, JL, 0u) | FIELD(G4_ADC2_JSQR, JEXTSEL, 0u) |
                   FIELD(G4_ADC2_JSQR, JEXTEN, 1u) | FIELD(G4_ADC2_JSQR, JSQ1, 8u);
    G4_ADC1_ISR = G4_ADC1_ISR_JEOS_Msk | G4_ADC1_ISR_JEOC_Msk;
    G4_ADC1_IER = G4_ADC1_IER_JEOSIE_Msk; /* the period interrupt */
    G4_ADC1_CR |= G4_ADC1_CR_JADSTART_Msk;
    G4_ADC2_CR |= G4_ADC2_CR_JADSTART_Msk;
}

/* ------------------------------------------------------------------ over-current */

static void overcurrent_init(void)
{
    /* DAC3 channel 1 (internal) sets COMP1's threshold: I_bus amplifier mid-scale + the
     * trip current in ADC counts (same scale as the phase currents) */
    G4_RCC_AHB2ENR |= G4_RCC_AHB2ENR_DAC3EN_Msk;
    G4_RCC_APB2ENR |= G4_RCC_APB2ENR_SYSCFGEN_Msk;
    (void)G4_RCC_AHB2ENR;
    uint32_t counts = (uint32_t)FD_BOARD_ADC_MID_COUNTS +
                      (uint32_t)(FD_BOARD_HW_OVERCURRENT_A / FD_BOARD_CURRENT_LSB_A);
    G4_DAC3_DHR12R1 = counts > 4095u ? 4095u : counts;
    G4_DAC3_CR = G4_DAC3_CR_EN1_Msk;
    /* COMP1: + PA1 (I_bus), - DAC3 CH1 (INMSEL 100), hysteresis, output to TIM1 break */
    G4_COMP_C1CSR = FIELD(G4_COMP_C1CSR, INMSEL, 4u) | FIELD(G4_COMP_C1CSR, INPSEL, 0u) |
                    FIELD(G4_COMP_C1CSR, HYST, 2u) | G4_COMP_C1CSR_EN_Msk;
}

/* ------------------------------------------------------------------ capture, encoder, time */

/* Line voltages (the paper's Fig. 10): per line a comparator pair (> +Vdc/2, < -Vdc/2) on
 * an add-on divider board. Per line one timer, reset by TIM1 TRGO at each valley, counts
 * at 170 MHz: CH1 captures the rising and CH2 (indirect, TI1) the falling edge of the
 * positive comparator, CH3/CH4 those of the negative one (TI3). One pulse per line and
 * period (centre-aligned PWM): high time = CCR2 - CCR1 (if both captured this period). */
static void capture_timer_init(volatile uint32_t *cr1, volatile uint32_t *smcr,
                               volatile uint32_t *ccmr1, volatile uint32_t *ccmr2,
                               volatile uint32_t *ccer, volatile uint32_t *psc,
                               volatile uint32_t *arr, volatile uint32_t *egr, uint32_t neg_ti4)
{
    *psc = 0u;
    *arr = 0xFFFFu;
    /* CC1S = 01 (TI1), CC2S = 10 (TI1); the negative comparator on TI3 (CC3S = 01, CC4S =
     * 10) or on TI4 (CC3S = 10, CC4S = 01); input filter 2 samples */
    *ccmr1 = (1u << 0) | (2u << 4) | (2u << 8) | (2u << 12);
    *ccmr2 = (neg_ti4 ? (2u << 0) | (1u << 8) : (1u << 0) | (2u << 8)) | (2u << 4) | (2u << 12);
    /* CC1/CC3 rising, CC2/CC4 falling (CCxP = 1) */
    *ccer = (1u << 0) | (1u << 4) | (1u << 5) | (1u << 8) | (1u << 12) | (1u << 13);
    /* slave reset mode (SMS 100) on ITR0 = TIM1 TRGO (TS 000) */
    *smcr = (4u << 0) | (0u << 4);
    *egr = 1u;
    *cr1 = 1u;
}

static void timers_init(void)
{
    G4_RCC_APB1ENR1 |= G4_RCC_APB1ENR1_TIM2EN_Msk | G4_RCC_APB1ENR1_TIM3EN_Msk |
                       G4_RCC_APB1ENR1_TIM4EN_Msk | G4_RCC_APB1ENR1_TIM5EN_Msk;
    G4_RCC_APB2ENR |= G4_RCC_APB2ENR_TIM8EN_Msk;
    (void)G4_RCC_APB2ENR;
    /* TIM2 (32 bit): the microsecond time base */
    G4_TIM2_PSC = FD_BOARD_SYSCLK_HZ / 1000000u - 1u;
    G4_TIM2_ARR = 0xFFFFFFFFu;
    G4_TIM2_EGR = 1u;
    G4_TIM2_CR1 = 1u;
    /* TIM4: quadrature encoder (SMS 011, both inputs), 16 bit (the core unwraps) */
    G4_TIM4_CCMR1_INPUT = (1u << 0) | (1u << 8);
    G4_TIM4_SMCR = 3u;
    G4_TIM4_ARR = 0xFFFFu;
    G4_TIM4_CR1 = 1u;
    capture_timer_init(&G4_TIM3_CR1, &G4_TIM3_SMCR, &G4_TIM3_CCMR1_INPUT, &G4_TIM3_CCMR2_INPUT,
                       &G4_TIM3_CCER, &G4_TIM3_PSC, &G4_TIM3_ARR, &G4_TIM3_EGR, 1u);
    capture_timer_init(&G4_TIM5_CR1, &G4_TIM5_SMCR, &G4_TIM5_CCMR1_INPUT, &G4_TIM5_CCMR2_INPUT,
                       &G4_TIM5_CCER, &G4_TIM5_PSC, &G4_TIM5_ARR, &G4_TIM5_EGR, 0u);
    capture_timer_init(&G4_TIM8_CR1, &G4_TIM8_SMCR, &G4_TIM8_CCMR1_INPUT, &G4_TIM8_CCMR2_INPUT,
                       &G4_TIM8_CCER, &G4_TIM8_PSC, &G4_TIM8_ARR, &G4_TIM8_EGR, 0u);
}

/* ------------------------------------------------------------------ FDCAN1 */

/* message RAM of FDCAN1 (RM0440 44.3.3, fixed layout): 28 standard filters, 8 extended,
 * RX FIFO 0 and 1 of 3 elements, TX event FIFO of 3, 3 TX buffers; elements of 18 words */
#define MRAM(off) G4_REG(G4_SRAMCAN_BASE + (off))
#define MRAM_FLS 0x000u
#define MRAM_RF0 0x0B0u
#define MRAM_TXB 0x278u
#define MRAM_ELEM 72u
#define MRAM_SIZE 0x350u

static const uint8_t DLC_LEN[16] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64};

static uint32_t len_to_dlc(uint32_t len)
{
    uint32_t d = 0;
    while (d < 15u && DLC_LEN[d] < len) {
        ++d;
    }
    return d;
}

/* the host's frames (ids generated from the DBC): standard ids into RX FIFO 0 (classic
 * id/mask filter, mask 0x7FF); everything else rejected in hardware */
static const uint16_t RX_IDS[] = {FD_CAN_ARM_MODE_FRAME_ID, FD_CAN_DUTY_CMD_FRAME_ID,
                                  FD_CAN_HOST_REF_FRAME_ID, FD_CAN_DRIVE_PARAM_FRAME_ID,
                                  FD_CAN_HOST_HEARTBEAT_FRAME_ID};

static void fdcan_init(void)
{
    G4_RCC_CCIPR = (G4_RCC_CCIPR & ~G4_RCC_CCIPR_FDCANSEL_Msk) | FIELD(G4_RCC_CCIPR, FDCANSEL, 2u);
    G4_RCC_APB1ENR1 |= G4_RCC_APB1ENR1_FDCANEN_Msk;
    (void)G4_RCC_APB1ENR1;
    G4_FDCAN1_CCCR |= G4_FDCAN1_CCCR_INIT_Msk;
    while (!(G4_FDCAN1_CCCR & G4_FDCAN1_CCCR_INIT_Msk)) {
    }
    G4_FDCAN1_CCCR |= G4_FDCAN1_CCCR_CCE_Msk;
    G4_FDCAN1_CKDIV = 0u; /* 170 MHz kernel clock (PCLK1) */
    /* nominal 1 Mbit/s: 170 tq, sample point 80 % (1 + 135 + 34); data 5 Mbit/s: 34 tq,
     * sample point 76.5 % (1 + 25 + 8); transmitter delay compensation at the data
     * sample point (TDCO = DTSEG1 + 1 in mtq) */
    G4_FDCAN1_NBTP = FIELD(G4_FDCAN1_NBTP, NSJW, 33u) | FIELD(G4_FDCAN1_NBTP, NBRP, 0u) |
                     FIELD(G4_FDCAN1_NBTP, NTSEG1, 134u) | FIELD(G4_FDCAN1_NBTP, NTSEG2, 33u);
    G4_FDCAN1_DBTP = G4_FDCAN1_DBTP_TDC_Msk | FIELD(G4_FDCAN1_DBTP, DBRP, 0u) |
                     FIELD(G4_FDCAN1_DBTP, DTSEG1, 24u) | FIELD(G4_FDCAN1_DBTP, DTSEG2, 7u) |
                     FIELD(G4_FDCAN1_DBTP, DSJW, 7u);
    G4_FDCAN1_TDCR = FIELD(G4_FDCAN1_TDCR, TDCO, 26u) | FIELD(G4_FDCAN1_TDCR, TDCF, 0u);
    G4_FDCAN1_CCCR |= G4_FDCAN1_CCCR_FDOE_Msk | G4_FDCAN1_CCCR_BRSE_Msk;
    for (uint32_t off = 0; off < MRAM_SIZE; off += 4u) {
        MRAM(off) = 0u;
    }
    uint32_t n = (uint32_t)(sizeof(RX_IDS) / sizeof(RX_IDS[0]));
    for (uint32_t i = 0; i < n; ++i) {
        /* SFT 10 (classic id/mask), SFEC 001 (FIFO 0), SFID1 id, SFID2 mask */
        MRAM(MRAM_FLS + 4u * i) = (2u << 30) | (1u << 27) | ((uint32_t)RX_IDS[i] << 16) | 0x7FFu;
    }
    G4_FDCAN1_RXGFC = FIELD(G4_FDCAN1_RXGFC, LSS, n) | FIELD(G4_FDCAN1_RXGFC, ANFS, 2u) |
                      FIELD(G4_FDCAN1_RXGFC, ANFE, 2u) | G4_FDCAN1_RXGFC_RRFS_Msk |
                      G4_FDCAN1_RXGFC_RRFE_Msk;
    G4_FDCAN1_TXBC = 0u; /* TX FIFO mode */
    /* bus-off, error passive, RX FIFO 0 message lost and new message on interrupt line 1
     * (a new message wakes the background loop from wfi: it handles received frames) */
    G4_FDCAN1_IE = G4_FDCAN1_IE_BOE_Msk | G4_FDCAN1_IE_RF0LE_Msk | G4_FDCAN1_IE_RF0NE_Msk;
    G4_FDCAN1_ILS = G4_FDCAN1_ILS_BERR_Msk | G4_FDCAN1_ILS_RXFIFO0_Msk;
    G4_FDCAN1_ILE = G4_FDCAN1_ILE_EINT1_Msk;
    G4_FDCAN1_CCCR &= ~(G4_FDCAN1_CCCR_CCE_Msk | G4_FDCAN1_CCCR_INIT_Msk);
}

/* ------------------------------------------------------------------ IWDG */

static void iwdg_init(void)
{
    /* LSI 32 kHz / 4 = 8 kHz; 80 ticks = 10 ms */
    G4_IWDG_KR = 0xCCCCu;
    G4_IWDG_KR = 0x5555u;
    G4_IWDG_PR = 0u;
    G4_IWDG_RLR = 80u;
    while (G4_IWDG_SR & (G4_IWDG_SR_PVU_Msk | G4_IWDG_SR_RVU_Msk)) {
    }
    G4_IWDG_KR = 0xAAAAu;
}

static uint32_t iwdg_seen;

/* refresh only while the period interrupt keeps running */
static void iwdg_refresh(void)
{
    if (fd_board.periods != iwdg_seen) {
        iwdg_seen = fd_board.periods;
        G4_IWDG_KR = 0xAAAAu;
    }
}

void fd_board_background(void)
{
    while (fd_core_background(&fd_board_core) > 0u) { /* CAN reception, below the period */
    }
    iwdg_refresh();
}

void fd_board_wait(void) { __asm__ volatile("wfi"); }

/* ------------------------------------------------------------------ config */

void fd_board_config(fd_config_t *cfg, uint8_t decimation)
{
    fd_config_default(cfg);
    cfg->period_us = 1000000u / FD_BOARD_PWM_HZ;
    cfg->ts_s = 1.0f / (float)FD_BOARD_PWM_HZ;
    cfg->decimation = decimation;
    cfg->current_lsb_a = FD_BOARD_CURRENT_LSB_A;
    for (int j = 0; j < 3; ++j) {
        cfg->current_offset_counts[j] = FD_BOARD_ADC_MID_COUNTS;
    }
    cfg->current_clip_counts = FD_BOARD_ADC_MID_COUNTS;
    cfg->vdc_lsb_v = FD_BOARD_VDC_LSB_V;
    cfg->pwm_period_ticks = FD_BOARD_TIM1_ARR;
    cfg->status_period = FD_BOARD_PWM_HZ / 10u;
    /* board limits from the stage's ratings (a DRIVE_PARAM can only tighten them) */
    cfg->current_adc_max_counts = 2 * FD_BOARD_ADC_MID_COUNTS - 1;
    cfg->oc_limit_a = FD_BOARD_OVERCURRENT_A;
    cfg->vdc_max_v = FD_BOARD_VDC_MAX_V;
    cfg->vdc_min_v = FD_BOARD_VDC_MIN_V;
    cfg->vdc_modulation_min_v = FD_BOARD_VDC_MODULATION_MIN_V;
    cfg->temp_max_c = FD_BOARD_TEMP_MAX_C;
    cfg->temp_hysteresis_c = 10;
    cfg->bootstrap_periods = FD_BOARD_BOOTSTRAP_PERIODS;
    cfg->require_calibration = FD_BOARD_REQUIRE_CALIBRATION;
}

void fd_board_init(uint8_t decimation)
{
    (void)*(volatile const uint32_t *)fd_board_debug; /* kept in the image */
    pins_init();
    fd_config_t cfg;
    fd_board_config(&cfg, decimation);
    fd_core_init(&fd_board_core, &cfg, &fd_board);
    timers_init();
    overcurrent_init();
    adc_init();
    fdcan_init();
    tim1_init(); /* from here on the period interrupt runs */
    nvic_enable(G4_IRQ_TIM1_BRK_TIM15, 0u);
    nvic_enable(G4_IRQ_ADC1_2, 1u);
    nvic_enable(G4_IRQ_FDCAN1_IT1, 2u);
    iwdg_init();
}

/* ------------------------------------------------------------------ fd_hal.h */

void fd_hal_adc_read(void *hal, fd_adc_raw_t *out)
{
    (void)hal;
    out->current_counts[0] = (int32_t)G4_ADC1_JDR1;
    out->current_counts[1] = (int32_t)G4_ADC1_JDR2;
    out->current_counts[2] = (int32_t)G4_ADC1_JDR3;
    out->vdc_counts = (int32_t)G4_ADC1_JDR4;
    out->temp_c = ((int32_t)G4_ADC2_JDR1 - FD_BOARD_TEMP_ZERO_COUNTS) / FD_BOARD_TEMP_COUNTS_PER_C;
}

/* high time of one comparator this period: CCR(fall) - CCR(rise) when both captured */
static int32_t pulse(volatile uint32_t *sr, volatile uint32_t *ccr_rise,
                     volatile uint32_t *ccr_fall, uint32_t rise_flag, uint32_t fall_flag)
{
    uint32_t s = *sr;
    if ((s & (rise_flag | fall_flag)) != (rise_flag | fall_flag)) {
        return 0;
    }
    int32_t w = (int32_t)(*ccr_fall & 0xFFFFu) - (int32_t)(*ccr_rise & 0xFFFFu);
    *sr = ~(rise_flag | fall_flag); /* rc_w0 */
    return w > 0 ? w : 0;
}

static int32_t line_ticks(volatile uint32_t *sr, volatile uint32_t *ccr1, volatile uint32_t *ccr2,
                          volatile uint32_t *ccr3, volatile uint32_t *ccr4)
{
    int32_t pos = pulse(sr, ccr1, ccr2, 1u << 1, 1u << 2);
    int32_t neg = pulse(sr, ccr3, ccr4, 1u << 3, 1u << 4);
    return pos - neg;
}

void fd_hal_capture_read(void *hal, fd_capture_raw_t *out)
{
    (void)hal;
    out->high_ticks[0] = line_ticks(&G4_TIM3_SR, &G4_TIM3_CCR1, &G4_TIM3_CCR2, &G4_TIM3_CCR3,
                                    &G4_TIM3_CCR4);
    out->high_ticks[1] = line_ticks(&G4_TIM5_SR, &G4_TIM5_CCR1, &G4_TIM5_CCR2, &G4_TIM5_CCR3,
                                    &G4_TIM5_CCR4);
    out->high_ticks[2] = line_ticks(&G4_TIM8_SR, &G4_TIM8_CCR1, &G4_TIM8_CCR2, &G4_TIM8_CCR3,
                                    &G4_TIM8_CCR4);
    out->period_ticks = (int32_t)FD_BOARD_CAPTURE_TICKS;
    out->encoder_counts = (int32_t)(int16_t)(uint16_t)G4_TIM4_CNT;
}

void fd_hal_status_read(void *hal, fd_hal_status_t *out)
{
    (void)hal;
    out->break_event = fd_board.break_event;
    fd_board.break_event = 0u; /* an event: cleared by reading */
    out->gate_fault = (uint8_t)((G4_GPIOC_IDR & (1u << FD_PIN_NFAULT)) == 0u);
    out->can_bus_off = (uint8_t)((G4_FDCAN1_PSR & G4_FDCAN1_PSR_BO_Msk) != 0u);
    uint32_t ecr = G4_FDCAN1_ECR;
    out->can_tec = (uint8_t)((ecr & G4_FDCAN1_ECR_TEC_Msk) >> G4_FDCAN1_ECR_TEC_Pos);
    uint32_t rec = (ecr & G4_FDCAN1_ECR_REC_Msk) >> G4_FDCAN1_ECR_REC_Pos;
    out->can_rec = (uint8_t)(rec > 255u ? 255u : rec);
}

void fd_hal_pwm_write(void *hal, const uint32_t compare[3], bool enable)
{
    (void)hal;
    uint32_t arr = FD_BOARD_TIM1_ARR;
    /* PWM mode 2: high-side on-time 2 (ARR - CCR) of 2 ARR ticks; preloaded: active from
     * the next update event */
    G4_TIM1_CCR1 = arr - (compare[0] < arr ? compare[0] : arr);
    G4_TIM1_CCR2 = arr - (compare[1] < arr ? compare[1] : arr);
    G4_TIM1_CCR3 = arr - (compare[2] < arr ? compare[2] : arr);
    if (!enable) {
        G4_TIM1_BDTR &= ~G4_TIM1_BDTR_MOE_Msk; /* not preloaded: off at once */
        G4_GPIOC_BSRR = 1u << (FD_PIN_EN + 16u); /* gate driver disabled */
        fd_board.pwm_on = 0u;
        return;
    }
    if (!fd_board.pwm_on) {
        /* gate enable: the driver first, then the outputs (the core runs the bootstrap
         * charge: compare 0, low sides on, for cfg.bootstrap_periods) */
        fd_board.pwm_on = 1u;
        G4_GPIOC_BSRR = 1u << FD_PIN_EN;
        G4_TIM1_BDTR |= G4_TIM1_BDTR_MOE_Msk;
    }
}

/* Called last in the period interrupt: TIM1's update flag (cleared on entry) set again
 * means the next valley passed, and with it the preload deadline of the running period */
/* bus-off: FDCAN1_IT1 already cleared INIT (the recovery runs); again does no harm */
void fd_hal_can_recover(void *hal)
{
    (void)hal;
    G4_FDCAN1_CCCR &= ~G4_FDCAN1_CCCR_INIT_Msk;
}

/* Two 2 KB pages at the end of bank 2 (dual-bank mode, OPTR.DBANK = 1, the G474's factory
 * setting; RM0440 3.3.1), outside the image (g474.ld's FLASH region ends before them). The
 * code runs from bank 1 and CCM SRAM: the period interrupt keeps running while bank 2 is
 * erased or programmed (read-while-write). A page, in double-words (RM0440 3.3.7: the
 * programming unit, each programmed once after an erase):
 *   +0        FD_BOARD_STORE_MAGIC, layout version (16 bit) << 16 | record length
 *   +8        sequence number, its complement
 *   +16       the record, the last double-word padded with ones
 *   +16+pad   CRC-32 of bytes [0, 16 + length), its complement: the valid flag
 * A save goes to the page that does not hold the newest intact set: erase, header, record,
 * read back and compared, the valid flag last. A power loss at any point leaves the other
 * page, the previous set, intact; at boot the newest intact page is the set. */
#define FLASH_KEY1 0x45670123u /* RM0440 3.3.5: the FLASH_KEYR unlock sequence */
#define FLASH_KEY2 0xCDEF89ABu
#define FLASH_SR_ERRORS                                                                        \
    (G4_FLASH_SR_OPERR_Msk | G4_FLASH_SR_PROGERR_Msk | G4_FLASH_SR_WRPERR_Msk |                \
     G4_FLASH_SR_PGAERR_Msk | G4_FLASH_SR_SIZERR_Msk | G4_FLASH_SR_PGSERR_Msk |                \
     G4_FLASH_SR_MISERR_Msk | G4_FLASH_SR_FASTERR_Msk | G4_FLASH_SR_RDERR_Msk |                \
     G4_FLASH_SR_OPTVERR_Msk)
#define STORE_HEADER_BYTES 16u
#define STORE_PAD(len) (((len) + 7u) & ~7u)
#define STORE_RECORD_MAX (FD_BOARD_STORE_PAGE_BYTES - STORE_HEADER_BYTES - 8u)

static uint32_t store_addr(uint32_t page)
{
    return FD_BOARD_STORE_BANK2_ADDR +
           (FD_BOARD_STORE_FIRST_PAGE + page) * FD_BOARD_STORE_PAGE_BYTES;
}

static uint32_t flash_word(uint32_t addr) { return G4_REG(addr); }

static uint32_t store_length_word(uint32_t len) { return (FD_BOARD_STORE_VERSION << 16) | len; }

/* the page holds an intact set of `len` bytes (magic, version, length, sequence and CRC
 * with their complements); its sequence number */
static bool store_intact(uint32_t page, uint32_t len, uint32_t *seq)
{
    uint32_t a = store_addr(page);
    uint32_t c = a + STORE_HEADER_BYTES + STORE_PAD(len);
    if (flash_word(a) != FD_BOARD_STORE_MAGIC || flash_word(a + 4u) != store_length_word(len) ||
        flash_word(a + 8u) != ~flash_word(a + 12u) || flash_word(c) != ~flash_word(c + 4u)) {
        return false;
    }
    *seq = flash_word(a + 8u);
    return flash_word(c) == fd_crc32((const void *)(uintptr_t)a, STORE_HEADER_BYTES + len);
}

/* the page holding the newest intact set (wrap-safe sequence order), -1 if none */
static int store_newest(uint32_t len, uint32_t *seq)
{
    int best = -1;
    for (uint32_t p = 0; p < 2u; ++p) {
        uint32_t s = 0;
        if (store_intact(p, len, &s) && (best < 0 || (int32_t)(s - *seq) > 0)) {
            best = (int)p;
            *seq = s;
        }
    }
    return best;
}

static bool store_erased(uint32_t page)
{
    uint32_t a = store_addr(page);
    for (uint32_t off = 0; off < FD_BOARD_STORE_PAGE_BYTES; off += 4u) {
        if (flash_word(a + off) != 0xFFFFFFFFu) {
            return false;
        }
    }
    return true;
}

bool fd_hal_storage_read(void *hal, void *buf, uint32_t len)
{
    (void)hal;
    uint8_t *out = (uint8_t *)buf;
    uint32_t seq = 0;
    int page = len <= STORE_RECORD_MAX ? store_newest(len, &seq) : -1;
    if (page >= 0) {
        uint32_t a = store_addr((uint32_t)page) + STORE_HEADER_BYTES;
        for (uint32_t i = 0; i < len; ++i) {
            out[i] = *(volatile const uint8_t *)(uintptr_t)(a + i);
        }
        fd_board.store_seq = seq;
        fd_board.store_state = FD_BOARD_STORE_INTACT;
        return true;
    }
    if (store_erased(0u) && store_erased(1u)) {
        fd_board.store_state = FD_BOARD_STORE_EMPTY;
        return false; /* never stored */
    }
    /* written, but no page holds an intact set: the buffer as erased flash, which no record
     * check accepts (the core boots on its defaults and says so: PARAM_SOURCE "bad CRC") */
    for (uint32_t i = 0; i < len; ++i) {
        out[i] = 0xFFu;
    }
    fd_board.store_state = FD_BOARD_STORE_BAD;
    return true;
}

/* BSY cleared (the IWDG refreshed meanwhile: a page erase takes tens of ms, the watchdog
 * 10 ms; bounded by FD_BOARD_FLASH_WAIT_LOOPS), then the operation's error flags, cleared
 * (rc_w1); true without an error */
static bool flash_wait(void)
{
    uint32_t n = 0;
    while ((G4_FLASH_SR & G4_FLASH_SR_BSY_Msk) && n < FD_BOARD_FLASH_WAIT_LOOPS) {
        iwdg_refresh();
        ++n;
    }
    uint32_t sr = G4_FLASH_SR;
    G4_FLASH_SR = sr & (FLASH_SR_ERRORS | G4_FLASH_SR_EOP_Msk);
    if (sr & (FLASH_SR_ERRORS | G4_FLASH_SR_BSY_Msk)) {
        fd_board.store_error_sr = sr;
        return false;
    }
    return true;
}

/* page erase (RM0440 3.3.6): PER, the page number and bank, then STRT */
static bool flash_erase(uint32_t page)
{
    uint32_t cr = G4_FLASH_CR & ~(G4_FLASH_CR_PNB_Msk | G4_FLASH_CR_PG_Msk);
    G4_FLASH_CR = cr | G4_FLASH_CR_PER_Msk | G4_FLASH_CR_BKER_Msk |
                  FIELD(G4_FLASH_CR, PNB, FD_BOARD_STORE_FIRST_PAGE + page);
    G4_FLASH_CR |= G4_FLASH_CR_STRT_Msk;
    bool ok = flash_wait();
    G4_FLASH_CR &= ~(G4_FLASH_CR_PER_Msk | G4_FLASH_CR_BKER_Msk | G4_FLASH_CR_PNB_Msk);
    return ok;
}

/* one double-word (RM0440 3.3.7): PG set, the two words written in order */
static bool flash_program(uint32_t addr, uint32_t lo, uint32_t hi)
{
    G4_FLASH_CR |= G4_FLASH_CR_PG_Msk;
    G4_REG(addr) = lo;
    G4_REG(addr + 4u) = hi;
    bool ok = flash_wait();
    G4_FLASH_CR &= ~G4_FLASH_CR_PG_Msk;
    return ok;
}

/* bytes [off, off + 4) of the record, ones past its end */
static uint32_t record_word(const uint8_t *p, uint32_t off, uint32_t len)
{
    uint32_t w = 0;
    for (uint32_t i = 0; i < 4u; ++i) {
        uint32_t b = off + i < len ? p[off + i] : 0xFFu;
        w |= b << (8u * i);
    }
    return w;
}

/* the data cache may hold a page as it was before the erase: reset it (DCRST with DCEN
 * off, RM0440 3.3.2) */
static void flash_dcache_reset(void)
{
    G4_FLASH_ACR &= ~G4_FLASH_ACR_DCEN_Msk;
    G4_FLASH_ACR |= G4_FLASH_ACR_DCRST_Msk;
    G4_FLASH_ACR &= ~G4_FLASH_ACR_DCRST_Msk;
    G4_FLASH_ACR |= G4_FLASH_ACR_DCEN_Msk;
}

static bool store_program(uint32_t page, const uint8_t *src, uint32_t len, uint32_t seq)
{
    uint32_t a = store_addr(page);
    bool ok = flash_erase(page);
    ok = ok && flash_program(a, FD_BOARD_STORE_MAGIC, store_length_word(len));
    ok = ok && flash_program(a + 8u, seq, ~seq);
    for (uint32_t off = 0; ok && off < len; off += 8u) {
        ok = flash_program(a + STORE_HEADER_BYTES + off, record_word(src, off, len),
                           record_word(src, off + 4u, len));
    }
    flash_dcache_reset();
    for (uint32_t i = 0; ok && i < len; ++i) { /* read back before it is made valid */
        ok = *(volatile const uint8_t *)(uintptr_t)(a + STORE_HEADER_BYTES + i) == src[i];
    }
    if (ok) {
        uint32_t crc = fd_crc32((const void *)(uintptr_t)a, STORE_HEADER_BYTES + len);
        ok = flash_program(a + STORE_HEADER_BYTES + STORE_PAD(len), crc, ~crc);
        flash_dcache_reset();
    }
    uint32_t got = 0;
    return ok && store_intact(page, len, &got) && got == seq;
}

bool fd_hal_storage_write(void *hal, const void *buf, uint32_t len)
{
    (void)hal;
    if (len > STORE_RECORD_MAX || !(G4_FLASH_OPTR & G4_FLASH_OPTR_DBANK_Msk)) {
        return false; /* the layout above is the dual-bank one */
    }
    uint32_t seq = 0;
    int cur = store_newest(len, &seq);
    uint32_t page = cur == 0 ? 1u : 0u;
    seq = cur < 0 ? 1u : seq + 1u;
    uint32_t n = 0;
    while ((G4_FLASH_SR & G4_FLASH_SR_BSY_Msk) && n < FD_BOARD_FLASH_WAIT_LOOPS) {
        ++n;
    }
    if (G4_FLASH_CR & G4_FLASH_CR_LOCK_Msk) {
        G4_FLASH_KEYR = FLASH_KEY1;
        G4_FLASH_KEYR = FLASH_KEY2;
    }
    bool ok = !(G4_FLASH_CR & G4_FLASH_CR_LOCK_Msk);
    if (ok) {
        G4_FLASH_SR = FLASH_SR_ERRORS | G4_FLASH_SR_EOP_Msk; /* an earlier operation's */
        ok = store_program(page, (const uint8_t *)buf, len, seq);
        G4_FLASH_CR |= G4_FLASH_CR_LOCK_Msk;
    }
    if (ok) {
        fd_board.store_saves++;
        fd_board.store_seq = seq;
        fd_board.store_state = FD_BOARD_STORE_INTACT;
    } else {
        fd_board.store_errors++;
    }
    return ok;
}

/* the background's critical sections: PRIMASK (the break path needs no CPU) */
uint32_t fd_hal_irq_lock(void *hal)
{
    (void)hal;
    uint32_t primask;
    __asm__ volatile("mrs %0, primask" : "=r"(primask));
    __asm__ volatile("cpsid i" : : : "memory");
    return primask;
}

void fd_hal_irq_unlock(void *hal, uint32_t state)
{
    (void)hal;
    __asm__ volatile("msr primask, %0" : : "r"(state) : "memory");
}

bool fd_hal_period_overrun(void *hal)
{
    (void)hal;
    return (G4_TIM1_SR & G4_TIM1_SR_UIF_Msk) != 0u;
}

bool fd_hal_can_tx(void *hal, const fd_can_frame_t *frame)
{
    (void)hal;
    uint32_t q = G4_FDCAN1_TXFQS;
    if (q & G4_FDCAN1_TXFQS_TFQF_Msk) {
        return false;
    }
    uint32_t idx = (q & G4_FDCAN1_TXFQS_TFQPI_Msk) >> G4_FDCAN1_TXFQS_TFQPI_Pos;
    uint32_t base = MRAM_TXB + idx * MRAM_ELEM;
    uint32_t dlc = len_to_dlc(frame->len);
    MRAM(base) = (frame->id & 0x7FFu) << 18;
    MRAM(base + 4u) = (dlc << 16) | (frame->fd ? (1u << 21) | (1u << 20) : 0u);
    uint32_t n = DLC_LEN[dlc];
    for (uint32_t w = 0; w < n; w += 4u) { /* the DLC's padding reads as 0 */
        MRAM(base + 8u + w) = fd_can_word(frame, w);
    }
    G4_FDCAN1_TXBAR = 1u << idx;
    return true;
}

bool fd_hal_can_rx(void *hal, fd_can_frame_t *frame)
{
    (void)hal;
    uint32_t s = G4_FDCAN1_RXF0S;
    if ((s & G4_FDCAN1_RXF0S_F0FL_Msk) == 0u) {
        return false;
    }
    uint32_t idx = (s & G4_FDCAN1_RXF0S_F0GI_Msk) >> G4_FDCAN1_RXF0S_F0GI_Pos;
    uint32_t base = MRAM_RF0 + idx * MRAM_ELEM;
    uint32_t r0 = MRAM(base);
    uint32_t r1 = MRAM(base + 4u);
    frame->id = (r0 >> 18) & 0x7FFu;
    frame->fd = (uint8_t)((r1 >> 21) & 1u);
    frame->len = DLC_LEN[(r1 >> 16) & 0xFu];
    for (uint32_t w = 0; w < frame->len; w += 4u) {
        fd_can_set_word(frame, w, MRAM(base + 8u + w));
    }
    G4_FDCAN1_RXF0A = idx;
    return true;
}

uint32_t fd_hal_time_us(void *hal)
{
    (void)hal;
    return G4_TIM2_CNT;
}

/* ------------------------------------------------------------------ interrupts */

void ADC1_2_IRQHandler(void);
void TIM1_BRK_TIM15_IRQHandler(void);
void FDCAN1_IT1_IRQHandler(void);

/* the period interrupt: ADC1 end of the injected sequence started by TIM1's update */
void ADC1_2_IRQHandler(void)
{
    G4_ADC1_ISR = G4_ADC1_ISR_JEOS_Msk | G4_ADC1_ISR_JEOC_Msk;
    G4_TIM1_SR = ~G4_TIM1_SR_UIF_Msk;
    fd_core_period(&fd_board_core);
    fd_board.periods++;
}

/* hardware over-current: the break already cleared MOE (all switches off, no CPU) */
void TIM1_BRK_TIM15_IRQHandler(void)
{
    G4_TIM1_SR = ~G4_TIM1_SR_BIF_Msk;
    fd_board.break_trips++;
    fd_board.break_event = 1u; /* the core latches OVERCURRENT (fd_hal_status_read) */
    fd_board.pwm_on = 0u;
    G4_GPIOC_BSRR = 1u << (FD_PIN_EN + 16u);
}

/* bus-off: the controller set INIT; clearing it starts the recovery (129 x 11 recessive
 * bits), RX FIFO 0 overflow counted */
void FDCAN1_IT1_IRQHandler(void)
{
    uint32_t ir = G4_FDCAN1_IR;
    G4_FDCAN1_IR = ir;
    if (ir & G4_FDCAN1_IR_RF0L_Msk) {
        fd_board.rx_lost++;
    }
    if ((ir & G4_FDCAN1_IR_BO_Msk) && (G4_FDCAN1_PSR & G4_FDCAN1_PSR_BO_Msk)) {
        fd_board.bus_off_events++;
        G4_FDCAN1_CCCR &= ~G4_FDCAN1_CCCR_INIT_Msk;
    }
}
