# The CAN codec, generated from the DBC by cantools' C source generator (float32 scaling
# with rounding). Shared by the host build and the Cortex-M4F target build.
set(FD_GEN_DIR "${CMAKE_CURRENT_BINARY_DIR}/generated")
set(FD_GEN_C "${FD_GEN_DIR}/fd_can.c")
add_custom_command(
  OUTPUT "${FD_GEN_DIR}/fd_can.c" "${FD_GEN_DIR}/fd_can.h"
  COMMAND ${CMAKE_COMMAND} -E make_directory "${FD_GEN_DIR}"
  COMMAND "${FD_PYTHON}" -m cantools generate_c_source "${FD_DBC}"
          --use-float --use-round --database-name fd_can -o "${FD_GEN_DIR}"
  DEPENDS "${FD_DBC}"
  COMMENT "cantools: C codec from ${FD_DBC}"
  VERBATIM)
