component xyzbc_head_kins "Swivel-head B + rotary-table C kinematics whose pins hold the location errors probing sees (rumba-cnc)";

description """
Switchable kinematics for a travelling-column mill whose spindle head swivels about Y (joint 3,
B) over a rotary table C (joint 4) - rumba-cnc's machine config/machines/linuxcnc_swivelhead.yaml
(topology WCFXYZBT, METHOD.md section 2 conventions).

switchkins type 0 (start-up, M429): identity, joints = X Y Z B C (rumba probes in joint space).
switchkins type 1 (M428): tool-centre point: world X Y Z = stylus tip in table (C) coordinates.

Chain (joints x y z in mm, b c in deg):
  table   F_T_W = Rx(ea0c) Ry(eb0c) . Trans(pc) Rz(c) Trans(-pc),   pc = (c-x, c-y, 0)
  head    F_T_T = Trans(x, y, z) . Rx(ea0b) Rz(ec0b) . Trans(pb) Ry(b) Trans(-pb),
          pb = (b-x, 0, b-z)
  tip     (0, 0, -(pivot-length + tool-offset)) in the head frame
  world   P = F_T_W^-1 . F_T_T . tip;  inverse: (x, y, z) = F_T_W . P - (F_T_T(x=y=z=0) . tip)
The tilts are the ISO 230-1 location errors the control holds (deg, right-hand rule, applied in
the parent frame before the axis motion, Trans . Rot_x . Rot_y . Rot_z); both kinematics are exact
(the inverse is linear in x y z at fixed b c).
""";
// halcompile wants one pin and one function of its own: the kinematics, called by motion, need
// neither (their pins are made in EXTRA_SETUP); "_" mirrors the switch type when added to a thread
pin out s32 kinstype "switchkins type in use (0 identity, 1 tool-centre point)";
function _ nofp;
option extra_setup;
option period no;
license "GPL";
author "rumba-cnc";
;;

#include "kinematics.h"
#include "rtapi_math.h"

// the geometry pins, made once at load (EXTRA_SETUP, before hal_ready)
static struct haldata {
    hal_float_t *c_x, *c_y;           // C axis line through (c-x, c-y), mm
    hal_float_t *b_x, *b_z;           // B pivot point in the Z slide's frame, mm
    hal_float_t *pivot_length;        // B pivot -> stylus tip along the spindle, mm
    hal_float_t *tool_offset;         // motion.tooloffset.z (0 under G49)
    hal_float_t *ea0c, *eb0c;         // C line tilts about x, y, deg
    hal_float_t *ea0b, *ec0b;         // B line tilts about x, z, deg
} *hd;
static int switch_type = 0;

typedef struct { double r[3][3]; double t[3]; } htm;

static htm h_eye(void) {
    htm h = {{{1, 0, 0}, {0, 1, 0}, {0, 0, 1}}, {0, 0, 0}};
    return h;
}

static htm h_trans(double x, double y, double z) {
    htm h = h_eye();
    h.t[0] = x; h.t[1] = y; h.t[2] = z;
    return h;
}

// rotation by ang (rad) about principal axis k (0 x, 1 y, 2 z), right-hand rule
static htm h_rot(int k, double ang) {
    htm h = h_eye();
    int i = (k + 1) % 3, j = (k + 2) % 3;
    double c = cos(ang), s = sin(ang);
    h.r[i][i] = c; h.r[j][j] = c; h.r[i][j] = -s; h.r[j][i] = s;
    return h;
}

static htm h_mul(htm a, htm b) {
    htm c;
    int i, j, k;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            c.r[i][j] = 0;
            for (k = 0; k < 3; k++) c.r[i][j] += a.r[i][k] * b.r[k][j];
        }
        c.t[i] = a.t[i];
        for (k = 0; k < 3; k++) c.t[i] += a.r[i][k] * b.t[k];
    }
    return c;
}

static void h_point(htm h, const double p[3], double out[3]) {
    int i;
    for (i = 0; i < 3; i++) out[i] = h.t[i] + h.r[i][0] * p[0] + h.r[i][1] * p[1] + h.r[i][2] * p[2];
}

// p = h^-1 . q (rigid: the transpose)
static void h_point_inv(htm h, const double q[3], double out[3]) {
    int i;
    double d[3] = {q[0] - h.t[0], q[1] - h.t[1], q[2] - h.t[2]};
    for (i = 0; i < 3; i++) out[i] = h.r[0][i] * d[0] + h.r[1][i] * d[1] + h.r[2][i] * d[2];
}

static double rad(double deg) { return deg * M_PI / 180.0; }

// the table's frame in the foundation at C = c deg
static htm table(double c) {
    double px = *hd->c_x, py = *hd->c_y;
    htm loc = h_mul(h_rot(0, rad(*hd->ea0c)), h_rot(1, rad(*hd->eb0c)));
    htm m = h_mul(h_trans(px, py, 0), h_mul(h_rot(2, rad(c)), h_trans(-px, -py, 0)));
    return h_mul(loc, m);
}

// the stylus tip in the foundation frame with X = Y = Z = 0 at B = b deg
static void head_tip(double b, double out[3]) {
    double px = *hd->b_x, pz = *hd->b_z;
    double tip[3] = {0, 0, -(*hd->pivot_length + *hd->tool_offset)};
    htm loc = h_mul(h_rot(0, rad(*hd->ea0b)), h_rot(2, rad(*hd->ec0b)));
    htm m = h_mul(h_trans(px, 0, pz), h_mul(h_rot(1, rad(b)), h_trans(-px, 0, -pz)));
    h_point(h_mul(loc, m), tip, out);
}

int kinematicsForward(const double *j, EmcPose *pos, const KINEMATICS_FORWARD_FLAGS *fflags,
                      KINEMATICS_INVERSE_FLAGS *iflags) {
    (void)fflags; (void)iflags;
    pos->a = 0; pos->u = 0; pos->v = 0; pos->w = 0;
    pos->b = j[3];
    pos->c = j[4];
    if (switch_type == 0) {
        pos->tran.x = j[0]; pos->tran.y = j[1]; pos->tran.z = j[2];
        return 0;
    }
    double tip[3], f[3], w[3];
    head_tip(j[3], tip);
    f[0] = j[0] + tip[0]; f[1] = j[1] + tip[1]; f[2] = j[2] + tip[2];
    h_point_inv(table(j[4]), f, w);
    pos->tran.x = w[0]; pos->tran.y = w[1]; pos->tran.z = w[2];
    return 0;
}

int kinematicsInverse(const EmcPose *pos, double *j, const KINEMATICS_INVERSE_FLAGS *iflags,
                      KINEMATICS_FORWARD_FLAGS *fflags) {
    (void)iflags; (void)fflags;
    j[3] = pos->b;
    j[4] = pos->c;
    if (switch_type == 0) {
        j[0] = pos->tran.x; j[1] = pos->tran.y; j[2] = pos->tran.z;
        return 0;
    }
    double p[3] = {pos->tran.x, pos->tran.y, pos->tran.z}, f[3], tip[3];
    h_point(table(pos->c), p, f);
    head_tip(pos->b, tip);
    j[0] = f[0] - tip[0]; j[1] = f[1] - tip[1]; j[2] = f[2] - tip[2];
    return 0;
}

int kinematicsHome(EmcPose *world, double *joint, KINEMATICS_FORWARD_FLAGS *fflags,
                   KINEMATICS_INVERSE_FLAGS *iflags) {
    *fflags = 0; *iflags = 0;
    return kinematicsForward(joint, world, fflags, iflags);
}

KINEMATICS_TYPE kinematicsType(void) { return KINEMATICS_BOTH; }

int kinematicsSwitchable(void) { return 1; }

int kinematicsSwitch(int new_type) {
    if (new_type != 0 && new_type != 1) return -1;  // motion reports the refusal
    switch_type = new_type;
    return 0;
}

EXPORT_SYMBOL(kinematicsForward);
EXPORT_SYMBOL(kinematicsInverse);
EXPORT_SYMBOL(kinematicsHome);
EXPORT_SYMBOL(kinematicsType);
EXPORT_SYMBOL(kinematicsSwitchable);
EXPORT_SYMBOL(kinematicsSwitch);

FUNCTION(_) { kinstype = switch_type; }

#define PIN(field, name) \
    if ((r = hal_pin_float_newf(HAL_IN, &hd->field, comp_id, "xyzbc-head-kins." name))) return r

EXTRA_SETUP() {
    int r;
    (void)prefix; (void)extra_arg; (void)__comp_inst;
    hd = hal_malloc(sizeof(*hd));
    if (!hd) return -1;
    PIN(c_x, "c-x");
    PIN(c_y, "c-y");
    PIN(b_x, "b-x");
    PIN(b_z, "b-z");
    PIN(pivot_length, "pivot-length");
    PIN(tool_offset, "tool-offset");
    PIN(ea0c, "ea0c-deg");
    PIN(eb0c, "eb0c-deg");
    PIN(ea0b, "ea0b-deg");
    PIN(ec0b, "ec0b-deg");
    *hd->c_x = *hd->c_y = *hd->b_x = *hd->b_z = *hd->tool_offset = 0;
    *hd->pivot_length = 0;
    *hd->ea0c = *hd->eb0c = *hd->ea0b = *hd->ec0b = 0;
    return 0;
}
