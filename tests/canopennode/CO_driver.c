/*
 * CAN transport of the labbench test drive, written from CANopenNode's 301/CO_driver.h.
 *
 * No controller: a received frame comes in through cod_rx() (from drive_process.py, which
 * reads python-can's udp_multicast bus) and goes to the first receive buffer whose filter
 * matches (the lowest index wins, as CO_CANrxBufferInit() documents); CO_CANsend() puts a
 * frame in a queue that cod_tx() empties (the caller sends each one on the bus). Sending
 * never waits, so no transmit buffer is ever left full.
 */
#include "301/CO_driver.h"

#define TX_QUEUE 64U /* frames; the caller empties it after every processing step */

static CO_CANmodule_t* module; /* the one CAN module (CO_CANmodule_init) */
static CO_CANtx_t tx_queue[TX_QUEUE];
static uint16_t tx_head, tx_count;

void
CO_CANsetConfigurationMode(void* CANptr) {
    (void)CANptr;
}

void
CO_CANsetNormalMode(CO_CANmodule_t* CANmodule) {
    CANmodule->CANnormal = true;
}

CO_ReturnError_t
CO_CANmodule_init(CO_CANmodule_t* CANmodule, void* CANptr, CO_CANrx_t rxArray[], uint16_t rxSize,
                  CO_CANtx_t txArray[], uint16_t txSize, uint16_t CANbitRate) {
    (void)CANbitRate;
    if ((CANmodule == NULL) || (rxArray == NULL) || (txArray == NULL)) {
        return CO_ERROR_ILLEGAL_ARGUMENT;
    }
    CANmodule->CANptr = CANptr;
    CANmodule->rxArray = rxArray;
    CANmodule->rxSize = rxSize;
    CANmodule->txArray = txArray;
    CANmodule->txSize = txSize;
    CANmodule->CANerrorStatus = 0;
    CANmodule->CANnormal = false;
    CANmodule->useCANrxFilters = false;
    CANmodule->bufferInhibitFlag = false;
    CANmodule->firstCANtxMessage = true;
    CANmodule->CANtxCount = 0;
    CANmodule->errOld = 0;
    for (uint16_t i = 0; i < rxSize; i++) {
        rxArray[i].ident = 0;
        rxArray[i].mask = 0xFFFF;
        rxArray[i].object = NULL;
        rxArray[i].pCANrx_callback = NULL;
    }
    for (uint16_t i = 0; i < txSize; i++) {
        txArray[i].bufferFull = false;
    }
    module = CANmodule;
    tx_head = tx_count = 0;
    return CO_ERROR_NO;
}

void
CO_CANmodule_disable(CO_CANmodule_t* CANmodule) {
    if (CANmodule != NULL) {
        CANmodule->CANnormal = false;
    }
}

CO_ReturnError_t
CO_CANrxBufferInit(CO_CANmodule_t* CANmodule, uint16_t index, uint16_t ident, uint16_t mask, bool_t rtr,
                   void* object, void (*CANrx_callback)(void* object, void* message)) {
    if ((CANmodule == NULL) || (object == NULL) || (CANrx_callback == NULL) || (index >= CANmodule->rxSize)) {
        return CO_ERROR_ILLEGAL_ARGUMENT;
    }
    CO_CANrx_t* buffer = &CANmodule->rxArray[index];
    buffer->object = object;
    buffer->pCANrx_callback = CANrx_callback;
    buffer->ident = (uint16_t)((ident & 0x07FFU) | (rtr ? 0x0800U : 0U));
    buffer->mask = (uint16_t)((mask & 0x07FFU) | 0x0800U); /* a data frame never matches an RTR filter */
    return CO_ERROR_NO;
}

CO_CANtx_t*
CO_CANtxBufferInit(CO_CANmodule_t* CANmodule, uint16_t index, uint16_t ident, bool_t rtr, uint8_t noOfBytes,
                   bool_t syncFlag) {
    if ((CANmodule == NULL) || (index >= CANmodule->txSize)) {
        return NULL;
    }
    CO_CANtx_t* buffer = &CANmodule->txArray[index];
    buffer->ident = (uint32_t)(ident & 0x07FFU) | (rtr ? 0x0800U : 0U);
    buffer->DLC = noOfBytes;
    buffer->bufferFull = false;
    buffer->syncFlag = syncFlag;
    return buffer;
}

CO_ReturnError_t
CO_CANsend(CO_CANmodule_t* CANmodule, CO_CANtx_t* buffer) {
    if (tx_count == TX_QUEUE) {
        CANmodule->CANerrorStatus |= CO_CAN_ERRTX_OVERFLOW;
        return CO_ERROR_TX_OVERFLOW;
    }
    tx_queue[(tx_head + tx_count) % TX_QUEUE] = *buffer;
    tx_count++;
    CANmodule->firstCANtxMessage = false;
    return CO_ERROR_NO;
}

void
CO_CANclearPendingSyncPDOs(CO_CANmodule_t* CANmodule) {
    (void)CANmodule; /* frames leave at once: nothing is pending */
}

void
CO_CANmodule_process(CO_CANmodule_t* CANmodule) {
    (void)CANmodule; /* no controller, no bus errors to read */
}

/* One received frame in: to the first receive buffer that accepts it. */
void
cod_rx(uint16_t ident, uint8_t rtr, uint8_t dlc, const uint8_t* data) {
    if ((module == NULL) || !module->CANnormal) {
        return;
    }
    CO_CANrxMsg_t msg = {.ident = (uint16_t)(ident & 0x07FFU), .dlc = dlc > 8U ? 8U : dlc};
    memcpy(msg.data, data, msg.dlc);
    uint16_t key = (uint16_t)(msg.ident | (rtr ? 0x0800U : 0U));
    for (uint16_t i = 0; i < module->rxSize; i++) {
        CO_CANrx_t* buffer = &module->rxArray[i];
        if ((buffer->pCANrx_callback != NULL) && (((key ^ buffer->ident) & buffer->mask) == 0U)) {
            buffer->pCANrx_callback(buffer->object, &msg);
            return;
        }
    }
}

/* One frame the stack sent, out: 1 and the frame, or 0 when none is waiting. */
int
cod_tx(uint16_t* ident, uint8_t* rtr, uint8_t* dlc, uint8_t* data) {
    if (tx_count == 0U) {
        return 0;
    }
    CO_CANtx_t* frame = &tx_queue[tx_head];
    *ident = (uint16_t)(frame->ident & 0x07FFU);
    *rtr = (frame->ident & 0x0800U) != 0U;
    *dlc = frame->DLC;
    memcpy(data, frame->data, 8);
    tx_head = (uint16_t)((tx_head + 1U) % TX_QUEUE);
    tx_count--;
    return 1;
}
