/*
 * feeddrive -- a LinuxCNC HAL component: the drives of a feeddrive-hil emulator over UDP.
 *
 * Built with halcompile (hil linuxcnc builds it; by hand: copy this file and
 * io_adapters/include/feeddrive_wire.h into one folder and run
 * `halcompile --install feeddrive.c` there).  Loaded with
 *
 *     loadrt feeddrive joints=3 address=127.0.0.1:5005
 *     addf feeddrive.read servo-thread      (first in the thread)
 *     addf feeddrive.write servo-thread     (last in the thread)
 *
 * it speaks the fixed binary wire (feeddrive_wire.h; the emulator runs with
 * `hil run MACHINE --adapter 'udp://127.0.0.1:5005?wire=fixed'`): one setpoint datagram
 * for all joints per servo period, sent without waiting, and the newest feedback taken
 * from whatever the emulator has sent since the last period (it answers every PWM
 * period).  Nothing here blocks: a period without a new feedback keeps the last one.
 *
 * Per joint N (feeddrive.N.*), in joint units (mm, deg) through the scale parameter:
 *
 *   pos-cmd        in   float  position command (from joint.N.motor-pos-cmd, or a PID)
 *   vel-cmd        in   float  speed feed-forward, units/s (joint.N.vel-cmd; 0: none)
 *   enable         in   bit    joint.N.amp-enable-out: walk the drive's CiA 402 state
 *                              machine to OPERATION ENABLED (controlword 06h, 07h, 0Fh);
 *                              low: shut down (06h, torque off)
 *   fault-reset    in   bit    a rising edge (as a rising enable) sends a fault reset
 *                              (controlword bit 7) to a drive in FAULT
 *   pos-fb         out  float  position actual value, units (joint.N.motor-pos-fb)
 *   fault          out  bit    the drive is in FAULT or FAULT REACTION ACTIVE, or the
 *                              emulator has not answered yet, or not for
 *                              feedback-timeout s (joint.N.amp-fault-in)
 *   home-sw        out  bit    the home switch, 60FDh bit 2 (joint.N.home-sw-in)
 *   limit-neg      out  bit    the negative limit switch, 60FDh bit 0
 *   limit-pos      out  bit    the positive limit switch, 60FDh bit 1
 *   index-enable   io   bit    joint.N.index-enable: set by LinuxCNC's homing; at the
 *                              next index mark the position is reset (pos-fb reads 0
 *                              there) and the pin cleared
 *   enabled        out  bit    the drive is in OPERATION ENABLED
 *   statusword     out  u32    6041h
 *   fault-code     out  u32    603Fh (0: none)
 *   counts         out  float  the drive's position actual value, increments
 *   index-counts   out  float  the increment reading 0 since the last index reset
 *   scale          param rw float  increments per joint unit (default 1)
 *
 * and for the link (feeddrive.*): connected (out bit: a feedback within feedback-timeout),
 * rx-frames, rx-bad (datagrams refused: another length, magic, version, kind or number of
 * axes; or another sender), tx-dropped (sends the socket refused), stale-periods (periods
 * that found no new feedback), period-ns (the time from the previous read to this one:
 * the servo thread's period as it ran, which shows its jitter; 0 at the first) -- all out
 * u32 -- and feedback-timeout (param rw float, s, default 0.1).
 */

#include "rtapi.h"
#include "rtapi_app.h"
#include "hal.h"

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "feeddrive_wire.h"

MODULE_AUTHOR("feeddrive-hil");
MODULE_DESCRIPTION("feeddrive-hil emulated feed drives over UDP (fixed binary wire)");
MODULE_LICENSE("GPL");

#define MAX_JOINTS 16

static int joints = 3;
RTAPI_MP_INT(joints, "number of joints (axes of the emulated machine), 1-16");
static char *address = "127.0.0.1:5005";
RTAPI_MP_STRING(address, "the emulator's UDP address, HOST:PORT");

/* CiA 402 controlwords and statusword states (the statusword under its state mask) */
#define CW_SHUTDOWN 0x06
#define CW_SWITCH_ON 0x07
#define CW_ENABLE_OPERATION 0x0F
#define CW_DISABLE_VOLTAGE 0x00
#define CW_FAULT_RESET 0x80
#define SW_FAULT_BIT 0x08

typedef struct {
    hal_float_t *pos_cmd, *vel_cmd, *pos_fb, *counts, *index_counts;
    hal_bit_t *enable, *fault_reset, *fault, *home_sw, *limit_neg, *limit_pos;
    hal_bit_t *index_enable, *enabled;
    hal_u32_t *statusword, *fault_code;
    hal_float_t scale;
} joint_t;

typedef struct {
    joint_t joint[MAX_JOINTS];
    hal_bit_t *connected;
    hal_u32_t *rx_frames, *rx_bad, *tx_dropped, *stale_periods, *period_ns;
    hal_float_t feedback_timeout;
} feeddrive_t;

/* what one joint keeps between periods (not HAL data) */
typedef struct {
    double offset_counts;   /* the increment that reads as position 0 */
    int32_t marks;          /* index marks of the latest feedback */
    int32_t armed_marks;    /* the marks when index-enable was seen set */
    int armed;
    int last_enable, last_reset, reset_pending;
    int have_fb;
} joint_state_t;

static int comp_id;
static feeddrive_t *hal;
static joint_state_t state[MAX_JOINTS];
static int sock = -1;
static struct sockaddr_in device;
static uint32_t session, frame, seq;
static uint32_t peer_session, peer_frame;
static int have_peer, welcomed;
static long long last_fb_ns, hello_ns, last_read_ns;
static unsigned char rx_buf[2048];
static unsigned char fb_buf[2048];   /* the newest good feedback */
static unsigned char tx_buf[sizeof(struct fdw_setpoint)
                            + MAX_JOINTS * sizeof(struct fdw_setpoint_axis)];

static long long now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void header(struct fdw_header *h, int kind, int n_axes)
{
    h->magic[0] = FDW_MAGIC0;
    h->magic[1] = FDW_MAGIC1;
    h->version = FDW_VERSION;
    h->kind = (uint8_t)kind;
    h->session = session;
    h->frame = frame;
    h->n_axes = (uint16_t)n_axes;
    h->accepted = 0;
}

static void send_hello(long long t)
{
    struct fdw_header h;
    header(&h, FDW_KIND_HELLO, 0);
    /* a HELLO carries the frame counter without advancing it */
    if (sendto(sock, &h, sizeof h, MSG_DONTWAIT, (struct sockaddr *)&device,
               sizeof device) == (ssize_t)sizeof h)
        hello_ns = t;
}

/* Is this datagram a good feedback of our joints (or a WELCOME, taken here)? */
static int good_feedback(const unsigned char *buf, ssize_t n)
{
    const struct fdw_feedback *fb = (const struct fdw_feedback *)buf;
    if (n < (ssize_t)sizeof(struct fdw_header) || buf[0] != FDW_MAGIC0
        || buf[1] != FDW_MAGIC1 || fb->version != FDW_VERSION)
        return 0;
    if (fb->kind == FDW_KIND_WELCOME && n == (ssize_t)sizeof(struct fdw_header)) {
        if (fb->accepted == 1)
            welcomed = 1;
        return 0;
    }
    if (fb->kind != FDW_KIND_FEEDBACK || fb->n_axes != joints
        || n != (ssize_t)FDW_FEEDBACK_SIZE(joints) || fb->accepted != 0)
        return -1;
    if (have_peer && fb->session == peer_session && (int32_t)(fb->frame - peer_frame) <= 0)
        return 0; /* a duplicate or an older one: the newest is kept */
    return 1;
}

static void read_feedback(void *arg, long period)
{
    struct sockaddr_in from;
    socklen_t from_len;
    int got = 0, j;
    long long t = now_ns();
    (void)arg;
    (void)period;
    if (last_read_ns) {
        long long since = t - last_read_ns;
        *hal->period_ns = since < 0 ? 0 : since > 0xFFFFFFFFLL ? 0xFFFFFFFFu : (hal_u32_t)since;
    }
    last_read_ns = t;
    for (;;) {
        ssize_t n;
        int verdict;
        from_len = sizeof from;
        n = recvfrom(sock, rx_buf, sizeof rx_buf, MSG_DONTWAIT, (struct sockaddr *)&from,
                     &from_len);
        if (n < 0)
            break; /* EAGAIN: nothing more queued */
        *hal->rx_frames += 1;
        if (from.sin_addr.s_addr != device.sin_addr.s_addr || from.sin_port != device.sin_port) {
            *hal->rx_bad += 1;
            continue;
        }
        verdict = good_feedback(rx_buf, n);
        if (verdict < 0)
            *hal->rx_bad += 1;
        if (verdict <= 0)
            continue;
        memcpy(fb_buf, rx_buf, (size_t)n);
        peer_session = ((struct fdw_feedback *)fb_buf)->session;
        peer_frame = ((struct fdw_feedback *)fb_buf)->frame;
        have_peer = 1;
        got = 1;
    }
    if (got)
        last_fb_ns = t;
    else
        *hal->stale_periods += 1;
    *hal->connected = have_peer && t - last_fb_ns <= (long long)(hal->feedback_timeout * 1e9);
    for (j = 0; j < joints; j++) {
        joint_t *p = &hal->joint[j];
        joint_state_t *s = &state[j];
        const struct fdw_feedback_axis *a = &((struct fdw_feedback *)fb_buf)->axis[j];
        double scale = p->scale != 0.0 ? p->scale : 1.0;
        if (!have_peer) { /* no drive has answered yet: none to enable */
            *p->fault = 1;
            continue;
        }
        /* index-enable seen set for the first time: the mark to wait for is the next one
           after the marks of the feedback LinuxCNC decided on (the last period's) */
        if (*p->index_enable && !s->armed) {
            s->armed = 1;
            s->armed_marks = s->have_fb ? s->marks : a->index_marks;
        } else if (!*p->index_enable) {
            s->armed = 0;
        }
        if (s->armed && a->index_marks != s->armed_marks) {
            s->offset_counts = a->index_counts; /* the mark passed reads 0 */
            *p->index_enable = 0;
            s->armed = 0;
        }
        s->marks = a->index_marks;
        s->have_fb = 1;
        *p->counts = a->encoder_counts;
        *p->index_counts = s->offset_counts;
        *p->pos_fb = (a->encoder_counts - s->offset_counts) / scale;
        *p->statusword = a->statusword;
        *p->fault_code = (hal_u32_t)a->fault;
        *p->enabled = (a->statusword & 0x6F) == 0x27;
        *p->fault = (a->statusword & SW_FAULT_BIT) != 0 || !*hal->connected;
        *p->home_sw = (a->digital_inputs & FDW_DI_HOME_SWITCH) != 0;
        *p->limit_neg = (a->digital_inputs & FDW_DI_NEGATIVE_LIMIT) != 0;
        *p->limit_pos = (a->digital_inputs & FDW_DI_POSITIVE_LIMIT) != 0;
    }
}

/* The controlword that takes a drive in state `sw` one step toward what `enable` asks. */
static uint16_t controlword(uint16_t sw, int enable, joint_state_t *s)
{
    if ((sw & 0x4F) == 0x08) { /* FAULT: a reset once asked for, else nothing */
        if (s->reset_pending) {
            s->reset_pending = 0;
            return CW_FAULT_RESET;
        }
        return CW_DISABLE_VOLTAGE;
    }
    s->reset_pending = 0;
    if ((sw & 0x4F) == 0x0F) /* FAULT REACTION ACTIVE: it ends in FAULT */
        return CW_DISABLE_VOLTAGE;
    if (!enable)
        return CW_SHUTDOWN;
    switch (sw & 0x6F) {
    case 0x21: return CW_SWITCH_ON;         /* READY TO SWITCH ON */
    case 0x23: return CW_ENABLE_OPERATION;  /* SWITCHED ON */
    case 0x27: return CW_ENABLE_OPERATION;  /* OPERATION ENABLED */
    case 0x07: return CW_DISABLE_VOLTAGE;   /* QUICK STOP ACTIVE: leave it */
    default: return CW_SHUTDOWN;            /* SWITCH ON DISABLED and the rest */
    }
}

static void write_setpoint(void *arg, long period)
{
    struct fdw_setpoint *sp = (struct fdw_setpoint *)tx_buf;
    const struct fdw_feedback *fb = (const struct fdw_feedback *)fb_buf;
    size_t size = FDW_SETPOINT_SIZE(joints);
    long long t = now_ns();
    int j;
    (void)arg;
    (void)period;
    if (!welcomed && t - hello_ns >= FDW_HELLO_INTERVAL_NS)
        send_hello(t);
    header((struct fdw_header *)sp, FDW_KIND_SETPOINT, joints);
    sp->seq = seq;
    sp->reserved = 0;
    sp->t_ns = t;
    for (j = 0; j < joints; j++) {
        joint_t *p = &hal->joint[j];
        joint_state_t *s = &state[j];
        struct fdw_setpoint_axis *a = &sp->axis[j];
        uint16_t sw = have_peer ? fb->axis[j].statusword : 0;
        int enable = *p->enable != 0;
        double scale = p->scale != 0.0 ? p->scale : 1.0;
        if ((enable && !s->last_enable) || (*p->fault_reset && !s->last_reset))
            s->reset_pending = 1;
        s->last_enable = enable;
        s->last_reset = *p->fault_reset != 0;
        memset(a, 0, sizeof *a);
        a->controlword = controlword(sw, enable, s);
        a->mode = FDW_MODE_CSP;
        if (enable) {
            a->target_position_counts = *p->pos_cmd * scale + s->offset_counts;
            a->velocity_offset_counts_s = *p->vel_cmd * scale;
        } else { /* held where the axis is: enabling starts without a jump */
            a->target_position_counts = have_peer ? fb->axis[j].encoder_counts : 0.0;
        }
    }
    if (sendto(sock, tx_buf, size, MSG_DONTWAIT, (struct sockaddr *)&device, sizeof device)
        == (ssize_t)size)
        frame++;
    else
        *hal->tx_dropped += 1;
    seq++; /* a new target every period: the drive interpolates between them (60C2h) */
}

static int open_socket(void)
{
    char host[64];
    const char *colon = strrchr(address, ':');
    struct sockaddr_in local;
    size_t len = colon ? (size_t)(colon - address) : 0;
    if (!colon || len == 0 || len >= sizeof host) {
        rtapi_print_msg(RTAPI_MSG_ERR, "feeddrive: address=%s: expected HOST:PORT\n", address);
        return -EINVAL;
    }
    memcpy(host, address, len);
    host[len] = 0;
    memset(&device, 0, sizeof device);
    device.sin_family = AF_INET;
    device.sin_port = htons((uint16_t)atoi(colon + 1));
    if (inet_pton(AF_INET, host, &device.sin_addr) != 1 || device.sin_port == 0) {
        rtapi_print_msg(RTAPI_MSG_ERR, "feeddrive: address=%s: expected an IPv4 HOST:PORT\n",
                        address);
        return -EINVAL;
    }
    sock = socket(AF_INET, SOCK_DGRAM, 0);
    if (sock < 0)
        return -errno;
    memset(&local, 0, sizeof local);
    local.sin_family = AF_INET;
    local.sin_addr = device.sin_addr; /* the loopback address the emulator is on */
    local.sin_port = 0;
    if (bind(sock, (struct sockaddr *)&local, sizeof local) < 0
        || fcntl(sock, F_SETFL, fcntl(sock, F_GETFL) | O_NONBLOCK) < 0) {
        int e = errno;
        close(sock);
        sock = -1;
        rtapi_print_msg(RTAPI_MSG_ERR, "feeddrive: cannot bind a UDP socket: %s\n",
                        strerror(e));
        return -e;
    }
    return 0;
}

#define PIN(kind, dir, ptr, ...)                                                      \
    do {                                                                              \
        if ((r = hal_pin_##kind##_newf(dir, ptr, comp_id, __VA_ARGS__)) != 0)         \
            goto fail;                                                                \
    } while (0)

int rtapi_app_main(void)
{
    int r, j;
    long long t = now_ns();
    if (joints < 1 || joints > MAX_JOINTS) {
        rtapi_print_msg(RTAPI_MSG_ERR, "feeddrive: joints=%d: expected 1-%d\n", joints,
                        MAX_JOINTS);
        return -EINVAL;
    }
    comp_id = hal_init("feeddrive");
    if (comp_id < 0)
        return comp_id;
    hal = hal_malloc(sizeof *hal);
    if (!hal) {
        r = -ENOMEM;
        goto fail;
    }
    memset(hal, 0, sizeof *hal);
    for (j = 0; j < joints; j++) {
        joint_t *p = &hal->joint[j];
        PIN(float, HAL_IN, &p->pos_cmd, "feeddrive.%d.pos-cmd", j);
        PIN(float, HAL_IN, &p->vel_cmd, "feeddrive.%d.vel-cmd", j);
        PIN(bit, HAL_IN, &p->enable, "feeddrive.%d.enable", j);
        PIN(bit, HAL_IN, &p->fault_reset, "feeddrive.%d.fault-reset", j);
        PIN(float, HAL_OUT, &p->pos_fb, "feeddrive.%d.pos-fb", j);
        PIN(bit, HAL_OUT, &p->fault, "feeddrive.%d.fault", j);
        PIN(bit, HAL_OUT, &p->home_sw, "feeddrive.%d.home-sw", j);
        PIN(bit, HAL_OUT, &p->limit_neg, "feeddrive.%d.limit-neg", j);
        PIN(bit, HAL_OUT, &p->limit_pos, "feeddrive.%d.limit-pos", j);
        PIN(bit, HAL_IO, &p->index_enable, "feeddrive.%d.index-enable", j);
        PIN(bit, HAL_OUT, &p->enabled, "feeddrive.%d.enabled", j);
        PIN(u32, HAL_OUT, &p->statusword, "feeddrive.%d.statusword", j);
        PIN(u32, HAL_OUT, &p->fault_code, "feeddrive.%d.fault-code", j);
        PIN(float, HAL_OUT, &p->counts, "feeddrive.%d.counts", j);
        PIN(float, HAL_OUT, &p->index_counts, "feeddrive.%d.index-counts", j);
        if ((r = hal_param_float_newf(HAL_RW, &p->scale, comp_id, "feeddrive.%d.scale", j)))
            goto fail;
        p->scale = 1.0;
    }
    PIN(bit, HAL_OUT, &hal->connected, "feeddrive.connected");
    PIN(u32, HAL_OUT, &hal->rx_frames, "feeddrive.rx-frames");
    PIN(u32, HAL_OUT, &hal->rx_bad, "feeddrive.rx-bad");
    PIN(u32, HAL_OUT, &hal->tx_dropped, "feeddrive.tx-dropped");
    PIN(u32, HAL_OUT, &hal->stale_periods, "feeddrive.stale-periods");
    PIN(u32, HAL_OUT, &hal->period_ns, "feeddrive.period-ns");
    if ((r = hal_param_float_newf(HAL_RW, &hal->feedback_timeout, comp_id,
                                  "feeddrive.feedback-timeout")))
        goto fail;
    hal->feedback_timeout = 0.1;
    if ((r = hal_export_funct("feeddrive.read", read_feedback, 0, 1, 0, comp_id)))
        goto fail;
    if ((r = hal_export_funct("feeddrive.write", write_setpoint, 0, 1, 0, comp_id)))
        goto fail;
    if ((r = open_socket()))
        goto fail;
    /* a session of our own (the emulator pins it), and the HELLO that opens the link */
    session = (uint32_t)(t ^ (t >> 32) ^ ((long long)getpid() << 16));
    hello_ns = t - FDW_HELLO_INTERVAL_NS;
    send_hello(t);
    hal_ready(comp_id);
    return 0;
fail:
    rtapi_print_msg(RTAPI_MSG_ERR, "feeddrive: setup failed (%d)\n", r);
    hal_exit(comp_id);
    return r;
}

void rtapi_app_exit(void)
{
    if (sock >= 0)
        close(sock);
    hal_exit(comp_id);
}
