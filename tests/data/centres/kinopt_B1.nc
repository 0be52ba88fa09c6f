; Kinematics optimisation with sphere centres measured beforehand (rumba-cnc test
; fixture, tests/regen_centres_fixtures.py). Format: Beckhoff TwinCAT CNC TF5245,
; "Sphere centre points already calculated", infosys.beckhoff.com/content/1033/tf5245_tc3_cnc_cycles_kinopt/326272267.html
; Ball B1 of the thesis artefact, annex-B poses; A is absent on this B/C machine.
#VAR
V.L.KIN_TYP = 80        (kinematic measured)
V.L.KIN_VARIANT = 0     (variant of kinematic measured)
V.L.NUMBER_OF_POSES = 14 (number of measurement poses)
#ENDVAR
L CYCLE [NAME = "SysCalibFitInit.ecy"     \
        @P1 = V.L.KIN_TYP                 \
        @P2 = V.L.KIN_VARIANT             \
        @P3 = V.L.NUMBER_OF_POSES         \
        ]
; Call cycle to add new measurement data
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = -100.068148 \  (X coordinate of centre point)
      @P2 = -80.195602 \  (Y coordinate of centre point)
      @P3 = 152.162135 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 0          \  (associated B coordinate)
      @P6 = 0          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 36.918191 \  (X coordinate of centre point)
      @P2 = -80.198643 \  (Y coordinate of centre point)
      @P3 = 178.248149 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 45          \  (associated B coordinate)
      @P6 = 0          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 74.747145 \  (X coordinate of centre point)
      @P2 = -119.388912 \  (Y coordinate of centre point)
      @P3 = 140.415296 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 45          \  (associated B coordinate)
      @P6 = 30          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 92.909851 \  (X coordinate of centre point)
      @P2 = -126.577861 \  (Y coordinate of centre point)
      @P3 = 122.027916 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 30          \  (associated B coordinate)
      @P6 = 60          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 145.468855 \  (X coordinate of centre point)
      @P2 = -99.840700 \  (Y coordinate of centre point)
      @P3 = 91.682708 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 30          \  (associated B coordinate)
      @P6 = 90          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 154.596492 \  (X coordinate of centre point)
      @P2 = -46.340383 \  (Y coordinate of centre point)
      @P3 = 116.083197 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 15          \  (associated B coordinate)
      @P6 = 120          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 161.543413 \  (X coordinate of centre point)
      @P2 = 19.589185 \  (Y coordinate of centre point)
      @P3 = 114.222561 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 15          \  (associated B coordinate)
      @P6 = 150          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 99.698346 \  (X coordinate of centre point)
      @P2 = 80.280225 \  (Y coordinate of centre point)
      @P3 = 152.157558 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = 0          \  (associated B coordinate)
      @P6 = 180          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = 5.201802 \  (X coordinate of centre point)
      @P2 = 119.472147 \  (Y coordinate of centre point)
      @P3 = 158.947388 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = -15          \  (associated B coordinate)
      @P6 = 210          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = -58.481105 \  (X coordinate of centre point)
      @P2 = 126.662785 \  (Y coordinate of centre point)
      @P3 = 141.885762 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = -15          \  (associated B coordinate)
      @P6 = 240          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = -145.813056 \  (X coordinate of centre point)
      @P2 = 99.925701 \  (Y coordinate of centre point)
      @P3 = 91.585660 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = -30          \  (associated B coordinate)
      @P6 = 270          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = -179.756069 \  (X coordinate of centre point)
      @P2 = 46.425338 \  (Y coordinate of centre point)
      @P3 = 71.991517 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = -30          \  (associated B coordinate)
      @P6 = 300          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = -197.392571 \  (X coordinate of centre point)
      @P2 = -19.501737 \  (Y coordinate of centre point)
      @P3 = 17.946655 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = -45          \  (associated B coordinate)
      @P6 = 330          \  (associated C coordinate)
      ]
L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \
      @P1 = -178.487674 \  (X coordinate of centre point)
      @P2 = -80.193021 \  (Y coordinate of centre point)
      @P3 = 36.852357 \  (Z coordinate of centre point)
      @P4 = 0          \  (associated A coordinate)
      @P5 = -45          \  (associated B coordinate)
      @P6 = 360          \  (associated C coordinate)
      ]
#VAR
V.P.MAX_PRECISION = 0.06   (precision)
V.P.LIST_FORMAT   = 1      (list format for result)
#ENDVAR
L CYCLE [NAME = "SysCalibFit.ecy"   \
        @P1 = V.P.LIST_FORMAT       \
        @P2 = V.P.MAX_PRECISION     \
        ]
M30
