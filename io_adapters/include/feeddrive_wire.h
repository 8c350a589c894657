/*
 * feeddrive_wire.h -- the fixed binary wire of feeddrive-hil (URL option wire=fixed).
 *
 * The reference for the byte offsets of io_adapters/codec_fixed.py, which documents what
 * every field means and what a receiver refuses; tests/test_codec_fixed.py compiles this
 * header and checks every offset, size and type against the Python codec.
 *
 * One UDP datagram carries one message: a header, the common part of its kind and, for a
 * record, n_axes axis blocks.  Every field is little-endian and naturally aligned; there is
 * no padding the compiler would add (reserved fields hold the places, and must be 0).  A
 * big-endian host must swap every field.
 *
 *   controller -> device   struct fdw_setpoint + n_axes x struct fdw_setpoint_axis
 *   device -> controller   struct fdw_feedback + n_axes x struct fdw_feedback_axis
 *   handshake              struct fdw_header alone (HELLO, WELCOME)
 *
 * Units as on the msgpack wire: positions in motor-encoder increments (CiA 402 position
 * factor 1), speeds in increments/s, currents in A, voltages in V, stamps in ns of the
 * sender's CLOCK_MONOTONIC.
 */
#ifndef FEEDDRIVE_WIRE_H
#define FEEDDRIVE_WIRE_H

#include <stdint.h>

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "feeddrive_wire.h: the wire is little-endian; swap every field on this host"
#endif

#define FDW_MAGIC0 0x46 /* 'F' */
#define FDW_MAGIC1 0x44 /* 'D' */
#define FDW_VERSION 1

#define FDW_KIND_SETPOINT 1
#define FDW_KIND_FEEDBACK 2
#define FDW_KIND_HELLO 3   /* controller -> device: the header alone */
#define FDW_KIND_WELCOME 4 /* device -> controller: the header, accepted = 1 or 0 */

/* CiA 402 modes of operation (6060h) the drive takes */
#define FDW_MODE_CSP 8
#define FDW_MODE_CSV 9
#define FDW_MODE_CST 10
#define FDW_MODE_VOLTAGE (-1)

/* 60FDh digital inputs (fdw_feedback_axis.digital_inputs) */
#define FDW_DI_NEGATIVE_LIMIT (1u << 0)
#define FDW_DI_POSITIVE_LIMIT (1u << 1)
#define FDW_DI_HOME_SWITCH (1u << 2)

/* a controller not yet welcomed repeats its HELLO at most this often, ns */
#define FDW_HELLO_INTERVAL_NS 100000000LL

struct fdw_header {          /* 16 bytes */
    uint8_t magic[2];        /* FDW_MAGIC0, FDW_MAGIC1 */
    uint8_t version;         /* FDW_VERSION */
    uint8_t kind;            /* FDW_KIND_* */
    uint32_t session;        /* drawn at random when the sender opens */
    uint32_t frame;          /* the sender's frame counter; HELLO/WELCOME do not advance it */
    uint16_t n_axes;         /* axis blocks that follow; 0 in HELLO and WELCOME */
    uint16_t accepted;       /* WELCOME: 1 taken, 0 not; else 0 */
};

struct fdw_setpoint_axis {   /* 64 bytes */
    uint16_t controlword;    /* 6040h */
    int8_t mode;             /* 6060h, FDW_MODE_* */
    uint8_t reserved0;
    uint32_t reserved1;
    double target_position_counts;    /* CSP */
    double target_velocity_counts_s;  /* CSV */
    double velocity_offset_counts_s;  /* CSP speed feed-forward */
    double iq_ref_a;                  /* CST; CSP/CSV current feed-forward */
    double id_ref_a;
    double ud_v;                      /* VOLTAGE */
    double uq_v;
};

struct fdw_setpoint {        /* 32 bytes, then n_axes axis blocks */
    uint8_t magic[2];
    uint8_t version;
    uint8_t kind;
    uint32_t session;
    uint32_t frame;
    uint16_t n_axes;
    uint16_t accepted;
    uint32_t seq;            /* the controller's cycle counter */
    uint32_t reserved;
    int64_t t_ns;            /* controller clock at sending, >= 0 */
    struct fdw_setpoint_axis axis[];
};

struct fdw_feedback_axis {   /* 64 bytes */
    uint16_t statusword;     /* 6041h */
    uint16_t digital_inputs; /* 60FDh, FDW_DI_* */
    int32_t fault;           /* 603Fh, 0: none */
    double encoder_counts;   /* position actual value 6064h */
    double scale_counts;     /* linear scale, 0 without one */
    double velocity_counts_s;/* 606Ch */
    double iq_a;
    double id_a;
    double index_counts;     /* where the index mark last passed lies (as encoder_counts) */
    int32_t index_marks;     /* index marks below the encoder: changes at every mark passed */
    uint32_t reserved;
};

struct fdw_feedback {        /* 64 bytes, then n_axes axis blocks */
    uint8_t magic[2];
    uint8_t version;
    uint8_t kind;
    uint32_t session;
    uint32_t frame;
    uint16_t n_axes;
    uint16_t accepted;
    uint32_t seq;            /* seq of the setpoint answered */
    uint32_t reserved;
    double time_s;           /* drive time at the end of the cycle */
    int64_t sp_t_ns;         /* t_ns of the latest setpoint received (controller clock) */
    int64_t sp_rx_ns;        /* drive clock when it arrived */
    int64_t t_ns;            /* drive clock at sending */
    int64_t tick_ns;         /* drive clock at the start of the tick (0: not given) */
    struct fdw_feedback_axis axis[];
};

#define FDW_SETPOINT_SIZE(n) (sizeof(struct fdw_setpoint) + (n) * sizeof(struct fdw_setpoint_axis))
#define FDW_FEEDBACK_SIZE(n) (sizeof(struct fdw_feedback) + (n) * sizeof(struct fdw_feedback_axis))

_Static_assert(sizeof(struct fdw_header) == 16, "fdw_header is 16 bytes");
_Static_assert(sizeof(struct fdw_setpoint) == 32, "fdw_setpoint is 32 bytes");
_Static_assert(sizeof(struct fdw_setpoint_axis) == 64, "fdw_setpoint_axis is 64 bytes");
_Static_assert(sizeof(struct fdw_feedback) == 64, "fdw_feedback is 64 bytes");
_Static_assert(sizeof(struct fdw_feedback_axis) == 64, "fdw_feedback_axis is 64 bytes");

#endif /* FEEDDRIVE_WIRE_H */
