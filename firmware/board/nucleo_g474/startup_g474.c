/* STM32G474 start-up: the full vector table (16 core exceptions + the device's interrupt
 * lines, generated from the register data: G4_IRQ_LIST), .data/.bss set-up, the stack
 * painted for the high-water mark, FPU on, main(). Unused lines go to Default_Handler. */
#include <stdint.h>

#include "g474_regs.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack, _stack_size, _siccm, _sccm,
    _eccm;
int main(void);
void Reset_Handler(void);
void Default_Handler(void);

#define FD_STACK_PAINT 0xA5A5A5A5u

void Default_Handler(void)
{
    for (;;) {
    }
}

#define FD_WEAK __attribute__((weak, alias("Default_Handler")))
void NMI_Handler(void) FD_WEAK;
void HardFault_Handler(void) FD_WEAK;
void MemManage_Handler(void) FD_WEAK;
void BusFault_Handler(void) FD_WEAK;
void UsageFault_Handler(void) FD_WEAK;
void SVC_Handler(void) FD_WEAK;
void DebugMon_Handler(void) FD_WEAK;
void PendSV_Handler(void) FD_WEAK;
void SysTick_Handler(void) FD_WEAK;
#define FD_DECLARE(n, name) void name##_IRQHandler(void) FD_WEAK;
G4_IRQ_LIST(FD_DECLARE)

void Reset_Handler(void)
{
    uint32_t *src = &_siccm;
    if (src != &_sccm) { /* the period interrupt's code into CCM SRAM (sections.ld) */
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
    /* paint the main stack below the reset handler's frame (high-water mark) */
    uint32_t *bottom = (uint32_t *)((uintptr_t)&_estack - (uintptr_t)&_stack_size);
    uint32_t *sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    for (uint32_t *p = bottom; p < sp - 16; ++p) {
        *p = FD_STACK_PAINT;
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

#define FD_VECTOR(n, name) name##_IRQHandler,
__attribute__((section(".isr_vector"), used)) const vector_t fd_vectors[16 + G4_IRQ_COUNT] = {
    (vector_t)(uintptr_t)&_estack, /* initial main stack pointer */
    Reset_Handler,
    NMI_Handler,
    HardFault_Handler,
    MemManage_Handler,
    BusFault_Handler,
    UsageFault_Handler,
    0, 0, 0, 0, /* reserved */
    SVC_Handler,
    DebugMon_Handler,
    0, /* reserved */
    PendSV_Handler,
    SysTick_Handler,
    G4_IRQ_LIST(FD_VECTOR)
};
