/* Test hook of the SIL build: decode a host->drive frame with the generated codec exactly as
 * the core's receive path does (unpack + the DBC's float32 scaling), values in SI units in
 * signal order of the DBC. Returns the number of values, < 0 on a malformed frame. */
#include "fd_can.h"
#include "fd_sil.h"

int fd_sil_decode_host(uint32_t id, const uint8_t *data, uint32_t len, float out[10])
{
    switch (id) {
    case FD_CAN_ARM_MODE_FRAME_ID: {
        struct fd_can_arm_mode_t m;
        if (fd_can_arm_mode_unpack(&m, data, len) != 0) {
            return -1;
        }
        out[0] = fd_can_arm_mode_arm_decode(m.arm);
        out[1] = fd_can_arm_mode_reset_fault_decode(m.reset_fault);
        out[2] = fd_can_arm_mode_sample_layout_decode(m.sample_layout);
        out[3] = fd_can_arm_mode_control_split_decode(m.control_split);
        out[4] = fd_can_arm_mode_mode_decode(m.mode);
        out[5] = fd_can_arm_mode_arm_key_decode(m.arm_key);
        out[6] = fd_can_arm_mode_cmd_timeout_decode(m.cmd_timeout);
        out[7] = fd_can_arm_mode_decimation_decode(m.decimation);
        out[8] = fd_can_arm_mode_arm_counter_decode(m.arm_counter);
        return 9;
    }
    case FD_CAN_DUTY_CMD_FRAME_ID: {
        struct fd_can_duty_cmd_t m;
        if (fd_can_duty_cmd_unpack(&m, data, len) != 0) {
            return -1;
        }
        out[0] = fd_can_duty_cmd_cmd_seq_decode(m.cmd_seq);
        out[1] = fd_can_duty_cmd_cmd_duty_a_decode(m.cmd_duty_a);
        out[2] = fd_can_duty_cmd_cmd_duty_b_decode(m.cmd_duty_b);
        out[3] = fd_can_duty_cmd_cmd_duty_c_decode(m.cmd_duty_c);
        out[4] = fd_can_duty_cmd_cmd_enable_decode(m.cmd_enable);
        return 5;
    }
    case FD_CAN_HOST_REF_FRAME_ID: {
        struct fd_can_host_ref_t m;
        if (fd_can_host_ref_unpack(&m, data, len) != 0) {
            return -1;
        }
        out[0] = fd_can_host_ref_ref_seq_decode(m.ref_seq);
        out[1] = fd_can_host_ref_ref_id_decode(m.ref_id);
        out[2] = fd_can_host_ref_ref_iq_decode(m.ref_iq);
        out[3] = fd_can_host_ref_ref_theta_decode(m.ref_theta);
        out[4] = fd_can_host_ref_ref_omega_decode(m.ref_omega);
        out[5] = fd_can_host_ref_ref_enable_decode(m.ref_enable);
        return 6;
    }
    case FD_CAN_DRIVE_PARAM_FRAME_ID: {
        struct fd_can_drive_param_t m;
        if (fd_can_drive_param_unpack(&m, data, len) != 0) {
            return -1;
        }
        out[0] = fd_can_drive_param_prm_id_decode(m.prm_id);
        out[1] = fd_can_drive_param_prm_seq_decode(m.prm_seq);
        out[2] = fd_can_drive_param_prm_write_decode(m.prm_write);
        out[3] = fd_can_drive_param_prm_value_decode(m.prm_value);
        return 4;
    }
    case FD_CAN_HOST_HEARTBEAT_FRAME_ID: {
        struct fd_can_host_heartbeat_t m;
        if (fd_can_host_heartbeat_unpack(&m, data, len) != 0) {
            return -1;
        }
        out[0] = fd_can_host_heartbeat_hb_alive_decode(m.hb_alive);
        out[1] = fd_can_host_heartbeat_hb_protocol_version_decode(m.hb_protocol_version);
        return 2;
    }
    default:
        return -2;
    }
}

int fd_sil_has_answer(const fd_sil_t *s, const fd_core_t *c, uint16_t seq)
{
    if (fd_core_has_answer(c, seq)) {
        return 1;
    }
    for (uint32_t i = s->rx_tail; i != s->rx_head; ++i) {
        const fd_can_frame_t *f = &s->rx[i % FD_SIL_QUEUE];
        if (c->split && f->id == FD_CAN_HOST_REF_FRAME_ID) {
            struct fd_can_host_ref_t m;
            if (fd_can_host_ref_unpack(&m, f->data, f->len) == 0 && m.ref_seq == seq) {
                return 1;
            }
        } else if (!c->split && f->id == FD_CAN_DUTY_CMD_FRAME_ID) {
            struct fd_can_duty_cmd_t m;
            if (fd_can_duty_cmd_unpack(&m, f->data, f->len) == 0 && m.cmd_seq == seq) {
                return 1;
            }
        }
    }
    return 0;
}
