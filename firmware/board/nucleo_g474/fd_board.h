/* fluxdrive board port: NUCLEO-G474RE (STM32G474RE, 170 MHz) + EVALSTDRIVE101 3-phase
 * low-voltage power stage (STDRIVE101 gate driver, 100 V MOSFETs, three low-side shunts)
 * + a CAN FD transceiver rated for 5 Mbit/s (TCAN1044AV class) on FDCAN1.
 * docs/firmware.md (Board port) lists the parts, pins and what never ran on hardware.
 *
 * Timing: TIM1 counts centre-aligned at 170 MHz (ARR = 8500: 10 kHz); its update event at
 * every valley (repetition counter 1) loads the preloaded compare values and, as TRGO,
 * starts ADC1/ADC2's injected conversions (phase currents, bus voltage, stage temperature)
 * and resets the three capture timers. ADC1's end of injected sequence is the period
 * interrupt (fd_core_period). Compare values written in the interrupt at t_k apply from
 * the update at t_(k+1). */
#ifndef FD_BOARD_H
#define FD_BOARD_H

#include <stdint.h>

#include "fd_core.h"

#define FD_BOARD_SYSCLK_HZ 170000000u
#define FD_BOARD_HSE_HZ 24000000u    /* NUCLEO-G474RE X3 crystal */
#define FD_BOARD_PWM_HZ 10000u
#define FD_BOARD_TIM1_ARR (FD_BOARD_SYSCLK_HZ / (2u * FD_BOARD_PWM_HZ)) /* 8500 */
#define FD_BOARD_CAPTURE_TICKS (2u * FD_BOARD_TIM1_ARR) /* capture timer ticks per period */
#define FD_BOARD_DEADTIME_NS 2000u   /* the machine card's deadtime_s */
#define FD_BOARD_BOOTSTRAP_PERIODS 10u /* 1 ms low sides on before the first switching */

/* sensing scales: the stage's shunt amplifiers and bus divider as the project's plant
 * models them (12 bit, +-20 A, 0..100 V); set them from the stage's schematic */
#define FD_BOARD_ADC_MID_COUNTS 2048
#define FD_BOARD_CURRENT_LSB_A (40.0f / 4096.0f)
#define FD_BOARD_VDC_LSB_V (100.0f / 4096.0f)
/* stage temperature sensor: linear, 0 degC at 500 counts, 10 counts per degC */
#define FD_BOARD_TEMP_ZERO_COUNTS 500
#define FD_BOARD_TEMP_COUNTS_PER_C 10

/* ratings -> protections (board config): EVALSTDRIVE101 6..75 V, 15 A rms */
#define FD_BOARD_VDC_MAX_V 75.0f
#define FD_BOARD_VDC_MIN_V 10.0f
#define FD_BOARD_VDC_MODULATION_MIN_V 6.0f /* the stage's lowest supply */
#define FD_BOARD_TEMP_MAX_C 90
/* arming an uncalibrated drive refused (NOT_CALIBRATED): the bench bridge calibrates
 * (ARM_MODE mode CALIBRATE_ADC, the motor at standstill, PWM off) before its first arming */
#ifndef FD_BOARD_REQUIRE_CALIBRATION
#define FD_BOARD_REQUIRE_CALIBRATION 1u
#endif
/* software trip at 0.95 of the ADC's 20 A full scale (the SIL's cap, so one board model):
 * the default card's 2.1 pu trip (18.9 A) fits under it, and a host that asks for more is
 * refused at arming by the read-back */
#define FD_BOARD_OVERCURRENT_A 19.0f
#define FD_BOARD_HW_OVERCURRENT_A 19.5f /* comparator -> TIM1 break (hardware, no CPU) */
#define FD_BOARD_RATED_CURRENT_A 9.0f

/* parameter storage (fd_hal_storage_*): two 2 KB flash pages at the end of bank 2
 * (dual-bank mode), 0x0807F000 and 0x0807F800, outside the image (target/g474.ld) */
#define FD_BOARD_STORE_BANK2_ADDR 0x08040000u
#define FD_BOARD_STORE_PAGE_BYTES 2048u
#define FD_BOARD_STORE_FIRST_PAGE 126u /* bank 2 pages 126 and 127 */
#define FD_BOARD_STORE_MAGIC 0x53504446u /* "FDPS" */
#define FD_BOARD_STORE_VERSION 1u        /* the page layout (fd_hal_g474.c) */
/* a bound on waiting for a flash operation: some ten cycles a loop, about 0.2 s at 170 MHz
 * (a page erase takes tens of ms: the datasheet's tERASE) */
#define FD_BOARD_FLASH_WAIT_LOOPS 4000000u
/* fd_board_t.store_state: what the flash held at boot (and after the last save) */
#define FD_BOARD_STORE_EMPTY 0u  /* nothing stored: the core's defaults */
#define FD_BOARD_STORE_INTACT 1u /* the newest intact set, store_seq */
#define FD_BOARD_STORE_BAD 2u    /* pages written, none intact: the defaults */

/** The board's fd_config_t (10 kHz, D as built). */
void fd_board_config(fd_config_t *cfg, uint8_t decimation);

/** Board state the HAL keeps (read by tests and the virtual board through the ELF). */
typedef struct {
    uint32_t periods;          /* period interrupts run */
    uint32_t break_trips;      /* hardware over-current trips (TIM1 break) */
    uint32_t bus_off_events;   /* FDCAN bus-off entries (each recovered) */
    uint32_t rx_lost;          /* FDCAN RX FIFO 0 message lost */
    uint32_t clock_source;     /* 1: HSE, 2: HSI16 (HSE failed to start) */
    uint32_t store_state;      /* FD_BOARD_STORE_* */
    uint32_t store_seq;        /* sequence number of the stored set in use */
    uint32_t store_saves;      /* parameter sets written */
    uint32_t store_errors;     /* saves that failed (FLASH_SR of the last in store_error_sr) */
    uint32_t store_error_sr;
    uint8_t pwm_on;            /* gate driver and MOE on */
    uint8_t break_event;       /* a break tripped since fd_hal_status_read last ran */
} fd_board_t;

extern fd_board_t fd_board;
extern fd_core_t fd_board_core;

void fd_board_clock_init(void);
void fd_board_init(uint8_t decimation);
/** One pass of the background loop (IWDG refresh while the period interrupt runs). */
void fd_board_background(void);
/** The idle point of the background loop (wfi); the virtual board stops here. */
void fd_board_wait(void);

#endif /* FD_BOARD_H */
