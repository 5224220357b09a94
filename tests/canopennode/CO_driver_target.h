/*
 * CANopenNode target definitions of the labbench test drive (CANopenNode's 301/CO_driver.h
 * documents what a target must provide; this file is written from that contract).
 *
 * The "CAN module" is a pair of plain C functions (CO_driver.c): cod_rx() hands one received
 * frame to the stack and cod_tx() takes one frame the stack sent. Everything runs in one
 * thread (drive_process.py calls in turn), so the critical sections are empty.
 */
#ifndef CO_DRIVER_TARGET_H
#define CO_DRIVER_TARGET_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

/* Stack configuration (301/CO_config.h): what a CiA 402 slave needs, nothing else. */
#define CO_CONFIG_NMT           (0)
#define CO_CONFIG_HB_CONS       (CO_CONFIG_HB_CONS_ENABLE | CO_CONFIG_FLAG_OD_DYNAMIC)
#define CO_CONFIG_NODE_GUARDING (CO_CONFIG_NODE_GUARDING_SLAVE_ENABLE)
#define CO_CONFIG_EM            (CO_CONFIG_EM_PRODUCER | CO_CONFIG_EM_HISTORY)
#define CO_CONFIG_SDO_SRV       (CO_CONFIG_SDO_SRV_SEGMENTED | CO_CONFIG_FLAG_OD_DYNAMIC)
#define CO_CONFIG_SDO_CLI       (0)
#define CO_CONFIG_TIME          (0)
#define CO_CONFIG_SYNC          (CO_CONFIG_SYNC_ENABLE | CO_CONFIG_FLAG_OD_DYNAMIC)
#define CO_CONFIG_PDO                                                                           \
    (CO_CONFIG_RPDO_ENABLE | CO_CONFIG_TPDO_ENABLE | CO_CONFIG_RPDO_TIMERS_ENABLE               \
     | CO_CONFIG_TPDO_TIMERS_ENABLE | CO_CONFIG_PDO_SYNC_ENABLE | CO_CONFIG_PDO_OD_IO_ACCESS    \
     | CO_CONFIG_FLAG_OD_DYNAMIC)
#define CO_CONFIG_LEDS    (0)
#define CO_CONFIG_LSS     (0)
#define CO_CONFIG_GFC     (0)
#define CO_CONFIG_SRDO    (0)
#define CO_CONFIG_STORAGE (0)
#define CO_CONFIG_GTW     (0)
#define CO_CONFIG_TRACE   (0)

/* Basic definitions: x86-64 and aarch64 Linux are little endian. */
#define CO_LITTLE_ENDIAN
#define CO_SWAP_16(x) x
#define CO_SWAP_32(x) x
#define CO_SWAP_64(x) x
typedef uint_fast8_t bool_t;
typedef float float32_t;
typedef double float64_t;

/* A received frame as the receive callbacks read it. */
typedef struct {
    uint16_t ident; /* 11-bit identifier */
    uint8_t dlc;
    uint8_t data[8];
} CO_CANrxMsg_t;

static inline uint16_t
CO_CANrxMsg_readIdent(void* rxMsg) {
    return ((CO_CANrxMsg_t*)rxMsg)->ident;
}

static inline uint8_t
CO_CANrxMsg_readDLC(void* rxMsg) {
    return ((CO_CANrxMsg_t*)rxMsg)->dlc;
}

static inline const uint8_t*
CO_CANrxMsg_readData(void* rxMsg) {
    return ((CO_CANrxMsg_t*)rxMsg)->data;
}

/* Receive filter of one stack object: identifier in bits 0-10, RTR in bit 11. */
typedef struct {
    uint16_t ident;
    uint16_t mask;
    void* object;
    void (*pCANrx_callback)(void* object, void* message);
} CO_CANrx_t;

typedef struct {
    uint32_t ident; /* identifier in bits 0-10, RTR in bit 11 */
    uint8_t DLC;
    uint8_t data[8];
    volatile bool_t bufferFull;
    volatile bool_t syncFlag;
} CO_CANtx_t;

typedef struct {
    void* CANptr;
    CO_CANrx_t* rxArray;
    uint16_t rxSize;
    CO_CANtx_t* txArray;
    uint16_t txSize;
    uint16_t CANerrorStatus;
    volatile bool_t CANnormal;
    volatile bool_t useCANrxFilters;
    volatile bool_t bufferInhibitFlag;
    volatile bool_t firstCANtxMessage;
    volatile uint16_t CANtxCount;
    uint32_t errOld;
} CO_CANmodule_t;

typedef struct {
    void* addr;
    size_t len;
    uint8_t subIndexOD;
    uint8_t attr;
    void* addrNV;
} CO_storage_entry_t;

/* One thread: no locks. */
#define CO_LOCK_CAN_SEND(CAN_MODULE)
#define CO_UNLOCK_CAN_SEND(CAN_MODULE)
#define CO_LOCK_EMCY(CAN_MODULE)
#define CO_UNLOCK_EMCY(CAN_MODULE)
#define CO_LOCK_OD(CAN_MODULE)
#define CO_UNLOCK_OD(CAN_MODULE)

#define CO_MemoryBarrier()
#define CO_FLAG_READ(rxNew) ((rxNew) != NULL)
#define CO_FLAG_SET(rxNew)                                                                      \
    {                                                                                           \
        CO_MemoryBarrier();                                                                     \
        rxNew = (void*)1L;                                                                      \
    }
#define CO_FLAG_CLEAR(rxNew)                                                                    \
    {                                                                                           \
        CO_MemoryBarrier();                                                                     \
        rxNew = NULL;                                                                           \
    }

#endif /* CO_DRIVER_TARGET_H */
