/* The image that would be flashed on the NUCLEO-G474RE set: clock tree, peripherals, the
 * drive core in the period interrupt, the background loop (watchdog) between interrupts. */
#include "fd_board.h"

#ifndef FD_BOARD_DECIMATION
#define FD_BOARD_DECIMATION 4u /* a real 1/5 Mbit/s CAN FD bus needs D >= 4 */
#endif

int main(void)
{
    fd_board_clock_init();
    fd_board_init((uint8_t)FD_BOARD_DECIMATION);
    for (;;) {
        fd_board_background();
        fd_board_wait();
    }
}
