/* Minimal Cortex-M4F start-up: vector table, .ccm/.data/.bss set-up, FPU on, main(). The
 * period interrupt of a real port is the PWM timer's (or the ADC end-of-conversion)
 * handler calling fd_core_period (docs/firmware.md, porting). */
#include <stdint.h>

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack, _siccm, _sccm, _eccm;
int main(void);
void Reset_Handler(void);
void Default_Handler(void);

void Default_Handler(void)
{
    for (;;) {
    }
}

void Reset_Handler(void)
{
    uint32_t *src = &_siccm;
    if (src != &_sccm) { /* the interrupt's code into CCM SRAM (sections.ld) */
        for (uint32_t *dst = &_sccm; dst < &_eccm;) {
            *dst++ = *src++;
        }
    }
    src = &_sidata;
    for (uint32_t *dst = &_sdata; dst < &_edata;) {
        *dst++ = *src++;
    }
    for (uint32_t *dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0u;
    }
    /* CPACR: full access to CP10/CP11 (the FPU) before any float instruction */
    volatile uint32_t *cpacr = (volatile uint32_t *)0xE000ED88u;
    *cpacr |= (0xFu << 20);
    __asm__ volatile("dsb\n\tisb");
    (void)main();
    for (;;) {
    }
}

typedef void (*vector_t)(void);

__attribute__((section(".isr_vector"), used)) const vector_t fd_vectors[16] = {
    (vector_t)(uintptr_t)&_estack, /* initial main stack pointer */
    Reset_Handler,                 /* reset */
    Default_Handler,               /* NMI */
    Default_Handler,               /* hard fault */
    Default_Handler,               /* memory management fault */
    Default_Handler,               /* bus fault */
    Default_Handler,               /* usage fault */
    0, 0, 0, 0,                    /* reserved */
    Default_Handler,               /* SVCall */
    Default_Handler,               /* debug monitor */
    0,                             /* reserved */
    Default_Handler,               /* PendSV */
    Default_Handler,               /* SysTick */
};
