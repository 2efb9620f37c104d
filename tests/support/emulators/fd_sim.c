/*
 * fd_sim.c - a simulated Force Dimension SDK library (libdrd/libdhd) holding one device.
 *
 * Written for haptic_collab's tests from the public function signatures only (the argument and
 * result types that the forcedimension-core Python binding declares for each symbol); no vendor
 * header or code was used. tests/client/test_forcedimension_backend.py compiles it, together
 * with a generated `int NAME(void){return -1;}` for every other dhd / drd symbol the installed
 * binding binds, into $FDSDK/lib/release/lin-<machine>-gcc/libdrd.so.3.17.6, the file the
 * binding looks for.
 *
 * Behaviour: one device, attached and not yet opened. dhdOpen / dhdOpenID(0) open it and return
 * a new ID each time (0, 1, ...); every device call must name that ID (or -1, the default
 * device), else it fails with an invalid-index error. A closed or unplugged device fails calls
 * with a communication / no-device error. Errors are kept per thread, like the SDK's. The force
 * the device displays is the last one set while its force mode is on, zero otherwise.
 *
 * Test hooks (sim_*) set what the device reports and tell what it was asked to do.
 */

#include <stdbool.h>
#include <stdio.h>
#include <string.h>
#include <time.h>

enum {
    ERR_NONE = 0,
    ERR_COM = 2,
    ERR_NO_DEVICE = 5,
    ERR_TIMEOUT = 7,
    ERR_INVALID_INDEX = 15,
};

static __thread int err_last = ERR_NONE;

static int attached = 1;           /* the device is plugged in */
static int system_type = 60;       /* DHD_DEVICE_FALCON */
static char system_name[64] = "falcon";
static int open_id = -1;           /* ID of the open device; -1: closed */
static int next_id = 0;
static int opens = 0, closes = 0;
static int force_on = 0;
static double position[3] = {0.0, 0.0, 0.0};
static double velocity[3] = {0.0, 0.0, 0.0};
static double force_set[3] = {0.0, 0.0, 0.0};
static unsigned int button_mask = 0;
static double max_force = -1.0;    /* no software limit */
static int fail_position = 0, fail_velocity = 0, fail_force = 0;

static int fail(int code)
{
    err_last = code;
    return -1;
}

static int done(void)
{
    err_last = ERR_NONE;
    return 0;
}

/* 0 when `id` names the open, attached device; else -1 with the error set */
static int check(signed char id)
{
    if (open_id < 0) return fail(ERR_NO_DEVICE);
    if (id != -1 && id != open_id) return fail(ERR_INVALID_INDEX);
    if (!attached) return fail(ERR_COM);
    return 0;
}

static void zero_force(void)
{
    force_set[0] = force_set[1] = force_set[2] = 0.0;
}

/* -- version and errors ------------------------------------------------------------------- */

void dhdGetSDKVersion(int *major, int *minor, int *release, int *revision)
{
    *major = 3;
    *minor = 17;
    *release = 6;
    *revision = 0;
}

static const char *describe(int code)
{
    switch (code) {
    case ERR_NONE: return "no error";
    case ERR_COM: return "simulated communication error";
    case ERR_NO_DEVICE: return "simulated: no device found";
    case ERR_TIMEOUT: return "simulated timeout";
    case ERR_INVALID_INDEX: return "simulated: invalid device index";
    default: return "simulated error";
    }
}

int dhdErrorGetLast(void) { return err_last; }
const char *dhdErrorGetLastStr(void) { return describe(err_last); }
const char *dhdErrorGetStr(int code) { return describe(code); }

double dhdGetTime(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* -- session ------------------------------------------------------------------------------ */

int dhdGetDeviceCount(void)
{
    err_last = ERR_NONE;
    return attached ? 1 : 0;
}

int dhdGetAvailableCount(void)
{
    err_last = ERR_NONE;
    return attached && open_id < 0 ? 1 : 0;
}

int dhdOpenID(signed char index)
{
    if (!attached) return fail(ERR_NO_DEVICE);
    if (index != 0) return fail(ERR_INVALID_INDEX);
    if (open_id >= 0) {   /* already open: its ID */
        err_last = ERR_NONE;
        return open_id;
    }
    open_id = next_id++;
    opens++;
    force_on = 0;
    zero_force();
    err_last = ERR_NONE;
    return open_id;
}

int dhdOpen(void) { return dhdOpenID(0); }

int dhdClose(signed char id)
{
    if (open_id < 0 || (id != -1 && id != open_id)) return fail(ERR_INVALID_INDEX);
    open_id = -1;
    closes++;
    force_on = 0;
    zero_force();
    return done();
}

int dhdStop(signed char id)
{
    if (check(id) < 0) return -1;
    force_on = 0;
    zero_force();
    return done();
}

int dhdGetSystemType(signed char id)
{
    if (check(id) < 0) return -1;
    if (system_type < 0) return fail(ERR_COM);
    err_last = ERR_NONE;
    return system_type;
}

const char *dhdGetSystemName(signed char id)
{
    if (check(id) < 0) return NULL;
    if (system_type < 0) {
        fail(ERR_COM);
        return NULL;
    }
    err_last = ERR_NONE;
    return system_name;
}

double dhdGetMaxForce(signed char id)
{
    if (check(id) < 0) return -1.0;
    err_last = ERR_NONE;
    return max_force;
}

/* -- servo calls -------------------------------------------------------------------------- */

int dhdEnableForce(bool on, signed char id)
{
    if (check(id) < 0) return -1;
    force_on = on ? 1 : 0;
    if (!force_on) zero_force();
    return done();
}

int dhdGetPosition(double *px, double *py, double *pz, signed char id)
{
    if (check(id) < 0) return -1;
    if (fail_position) return fail(ERR_COM);
    *px = position[0];
    *py = position[1];
    *pz = position[2];
    return done();
}

int dhdGetLinearVelocity(double *vx, double *vy, double *vz, signed char id)
{
    if (check(id) < 0) return -1;
    if (fail_velocity) return fail(ERR_TIMEOUT);
    *vx = velocity[0];
    *vy = velocity[1];
    *vz = velocity[2];
    return done();
}

unsigned int dhdGetButtonMask(signed char id)
{
    if (check(id) < 0) return 0;
    err_last = ERR_NONE;
    return button_mask;
}

int dhdGetButton(int index, signed char id)
{
    if (check(id) < 0) return -1;
    err_last = ERR_NONE;
    return (int)((button_mask >> index) & 1u);
}

int dhdSetForce(double fx, double fy, double fz, signed char id)
{
    if (check(id) < 0) return -1;
    if (fail_force) return fail(ERR_COM);
    force_set[0] = fx;
    force_set[1] = fy;
    force_set[2] = fz;
    return done();
}

int dhdGetForce(double *fx, double *fy, double *fz, signed char id)
{
    if (check(id) < 0) return -1;
    *fx = force_on ? force_set[0] : 0.0;
    *fy = force_on ? force_set[1] : 0.0;
    *fz = force_on ? force_set[2] : 0.0;
    return done();
}

/* -- test hooks --------------------------------------------------------------------------- */

void sim_set_position(double x, double y, double z)
{
    position[0] = x;
    position[1] = y;
    position[2] = z;
}

void sim_set_velocity(double x, double y, double z)
{
    velocity[0] = x;
    velocity[1] = y;
    velocity[2] = z;
}

void sim_set_buttons(unsigned int mask) { button_mask = mask; }

/* the model: a system type (-1: dhdGetSystemType fails) and its name */
void sim_set_type(int type, const char *name)
{
    system_type = type;
    snprintf(system_name, sizeof system_name, "%s", name ? name : "");
}

void sim_set_max_force(double limit) { max_force = limit; }
void sim_set_attached(int on) { attached = on; }
void sim_fail_position(int on) { fail_position = on; }
void sim_fail_velocity(int on) { fail_velocity = on; }
void sim_fail_force(int on) { fail_force = on; }

/* the force [N] the device displays now, device frame */
void sim_get_force(double *out)
{
    out[0] = force_on ? force_set[0] : 0.0;
    out[1] = force_on ? force_set[1] : 0.0;
    out[2] = force_on ? force_set[2] : 0.0;
}

int sim_force_enabled(void) { return force_on; }
int sim_open_id(void) { return open_id; }
int sim_opens(void) { return opens; }
int sim_closes(void) { return closes; }
