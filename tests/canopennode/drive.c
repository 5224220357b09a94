/*
 * The labbench test drive's node: CANopenNode v4 set up as a CiA 402 slave, with the calls
 * drive_process.py makes through ctypes (one thread, in turn, as CANopenNode's
 * README flowchart runs its mainline and its real-time part).
 *
 * The stack does all of CiA 301 as it is (NMT, SDO server, SYNC, PDOs and their timers,
 * heartbeat producer and consumer, node guarding, EMCY and the error history). The
 * CiA 402 application runs in Python; what it needs from here:
 *  - every write of the controlword 0x6040 (SDO or RPDO), in order, through cod_controlword():
 *    fault reset is an edge, so each write counts, not just the last value;
 *  - 0x6060 refused with SDO abort 0x06090030 for a mode 0x6502 does not offer, and 0x6061
 *    showing the mode taken (as a drive answers a mode write at once);
 *  - the stack's process steps split as CANopen.h offers them (cod_process, cod_sync,
 *    cod_rpdo, cod_tpdo), so the application steps its plant between the SYNC and the RPDO
 *    processing of that SYNC, and samples it before the TPDOs go out.
 */
#include "CANopen.h"
#include "OD.h"

#define NMT_CONTROL (CO_NMT_ERR_ON_ERR_REG | CO_ERR_REG_GENERIC_ERR | CO_ERR_REG_COMMUNICATION)
#define FIRST_HB_TIME_MS 0U
#define SDO_SERVER_TIMEOUT_MS 1000U
#define CW_QUEUE 64U
#define MODE_CST 10 /* cyclic synchronous torque, bit 9 of 0x6502 (CiA 402-2) */
#define MODE_PT 4   /* profile torque, bit 3 */

static CO_t* co;
static uint8_t node;
static OD_extension_t ext_6040, ext_6060;
static uint16_t cw_queue[CW_QUEUE];
static uint16_t cw_head, cw_count;

static ODR_t
write_controlword(OD_stream_t* stream, const void* buf, OD_size_t count, OD_size_t* countWritten) {
    ODR_t ret = OD_writeOriginal(stream, buf, count, countWritten);
    if ((ret == ODR_OK) && (cw_count < CW_QUEUE)) {
        cw_queue[(cw_head + cw_count) % CW_QUEUE] = CO_getUint16(buf);
        cw_count++;
    }
    return ret;
}

static ODR_t
write_mode(OD_stream_t* stream, const void* buf, OD_size_t count, OD_size_t* countWritten) {
    int8_t mode = (int8_t)CO_getUint8(buf);
    uint32_t supported = OD_RAM.x6502;
    bool_t offered = ((mode == MODE_CST) && ((supported >> 9) & 1U)) || ((mode == MODE_PT) && ((supported >> 3) & 1U));
    if (!offered) {
        return ODR_INVALID_VALUE;
    }
    ODR_t ret = OD_writeOriginal(stream, buf, count, countWritten);
    if (ret == ODR_OK) {
        OD_RAM.x6061 = mode;
    }
    return ret;
}

/* Communication reset section (also after NMT reset node / reset communication). */
static int
comm_reset(uint32_t* errInfo) {
    co->CANmodule->CANnormal = false;
    CO_CANsetConfigurationMode(NULL);
    CO_CANmodule_disable(co->CANmodule);
    CO_ReturnError_t err = CO_CANinit(co, NULL, 1000);
    if (err == CO_ERROR_NO) {
        err = CO_CANopenInit(co, NULL, NULL, OD, NULL, NMT_CONTROL, FIRST_HB_TIME_MS, SDO_SERVER_TIMEOUT_MS, 0,
                             false, node, errInfo);
    }
    if (err == CO_ERROR_NO) {
        err = CO_CANopenInitPDO(co, co->em, OD, node, errInfo);
    }
    if (err != CO_ERROR_NO) {
        return err;
    }
    ext_6040 = (OD_extension_t){.object = NULL, .read = OD_readOriginal, .write = write_controlword};
    ext_6060 = (OD_extension_t){.object = NULL, .read = OD_readOriginal, .write = write_mode};
    OD_extension_init(OD_ENTRY_H6040, &ext_6040);
    OD_extension_init(OD_ENTRY_H6060, &ext_6060);
    CO_CANsetNormalMode(co->CANmodule);
    return CO_ERROR_NO;
}

/* Create the node; 0 or a CO_ReturnError_t (errInfo: the OD entry at fault). */
int
cod_init(uint8_t nodeId, uint32_t* errInfo) {
    uint32_t heap = 0;
    node = nodeId;
    co = CO_new(NULL, &heap);
    if (co == NULL) {
        return CO_ERROR_OUT_OF_MEMORY;
    }
    return comm_reset(errInfo);
}

/* Mainline part: NMT, SDO server, EMCY, heartbeat consumer, node guarding.
 * Returns the NMT reset request that was carried out (0: none). */
int
cod_process(uint32_t dt_us) {
    CO_NMT_reset_cmd_t reset = CO_process(co, false, dt_us, NULL);
    if (reset != CO_RESET_NOT) {
        uint32_t errInfo = 0;
        (void)comm_reset(&errInfo);
    }
    return (int)reset;
}

/* Real-time part, in the order of CANopenNode's timer thread. */
int
cod_sync(uint32_t dt_us) {
    return CO_process_SYNC(co, dt_us, NULL) ? 1 : 0;
}

void
cod_rpdo(int syncWas, uint32_t dt_us) {
    CO_process_RPDO(co, syncWas != 0, dt_us, NULL);
}

void
cod_tpdo(int syncWas, uint32_t dt_us) {
    CO_process_TPDO(co, syncWas != 0, dt_us, NULL);
}

/* The next controlword written since the last call: 1 and the value, or 0. */
int
cod_controlword(uint16_t* value) {
    if (cw_count == 0U) {
        return 0;
    }
    *value = cw_queue[cw_head];
    cw_head = (uint16_t)((cw_head + 1U) % CW_QUEUE);
    cw_count--;
    return 1;
}

int
cod_nmt_state(void) {
    return (int)CO_NMT_getInternalState(co->NMT);
}

int
cod_is_error(uint8_t errorBit) {
    return CO_isError(co->em, errorBit) ? 1 : 0;
}

/* An error condition of the application (CO_errorReport: EMCY, 0x1001, 0x1003). */
void
cod_error(int set, uint8_t errorBit, uint16_t errorCode, uint32_t infoCode) {
    CO_error(co->em, set != 0, errorBit, set ? errorCode : CO_EMC_NO_ERROR, infoCode);
}

/* The application's own access to its variables (the original location, no extension). */
int
cod_read(uint16_t index, uint8_t sub, void* value, uint32_t size) {
    return (int)OD_get_value(OD_find(OD, index), sub, value, size, true);
}

int
cod_write(uint16_t index, uint8_t sub, void* value, uint32_t size) {
    return (int)OD_set_value(OD_find(OD, index), sub, value, size, true);
}

void
cod_close(void) {
    if (co != NULL) {
        CO_CANsetConfigurationMode(NULL);
        CO_delete(co);
        co = NULL;
    }
}
