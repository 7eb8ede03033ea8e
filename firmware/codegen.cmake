# Generated from the DBC at build time, shared by the host build and the Cortex-M4F target
# build: the CAN codec (cantools' C source generator, float32 scaling with rounding) and
# fd_protocol.h, every protocol constant (the project's generator; it needs only cantools).
set(FD_GEN_DIR "${CMAKE_CURRENT_BINARY_DIR}/generated")
set(FD_GEN_C "${FD_GEN_DIR}/fd_can.c")
set(FD_PROTOCOL_GEN "${CMAKE_CURRENT_LIST_DIR}/../tools/gen_protocol.py")
add_custom_command(
  OUTPUT "${FD_GEN_DIR}/fd_can.c" "${FD_GEN_DIR}/fd_can.h" "${FD_GEN_DIR}/fd_protocol.h"
  COMMAND ${CMAKE_COMMAND} -E make_directory "${FD_GEN_DIR}"
  COMMAND "${FD_PYTHON}" -m cantools generate_c_source "${FD_DBC}"
          --use-float --use-round --database-name fd_can -o "${FD_GEN_DIR}"
  COMMAND "${FD_PYTHON}" "${FD_PROTOCOL_GEN}" --dbc "${FD_DBC}"
          --c-header "${FD_GEN_DIR}/fd_protocol.h"
  DEPENDS "${FD_DBC}" "${FD_PROTOCOL_GEN}"
          "${CMAKE_CURRENT_LIST_DIR}/../python/fluxdrive/can/protocol/generate.py"
  COMMENT "cantools: C codec and protocol constants from ${FD_DBC}"
  VERBATIM)
